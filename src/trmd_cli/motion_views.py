"""What ``trmd motion`` shows of one exposure: the global motion the events give, how far it
carries each pixel, where the motion method trusts its deconvolution over EDI, and the events
before and after motion compensation.

Everything comes from the pieces ``--method motion`` runs (:func:`~trmd_cli.motion.estimate_motion`
inside :func:`~trmd_cli.deconv.motion_deblur`, EDI settled as :class:`~trmd_cli.methods.EdiMethod`
settles it), so the pictures show what ``trmd deblur --method motion`` did. Never prints.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .events import EventStream, Exposure
from .motion.model import GlobalMotion

__all__ = ["MotionViews", "motion_views", "displacement_field", "motion_summary"]


@dataclass(frozen=True, eq=False)
class MotionViews:
    """One exposure's motion, as :func:`motion_views` found it.

    Attributes:
        motion: the estimated global motion (pixels, exposure fractions).
        displacement: (H, W, 2) float32 (dx, dy) pixels, where each middle-frame pixel goes
            from the start of the exposure to its end.
        weight: (H, W) float32 [0, 1], the deconvolution's share in the output (0 = EDI).
        events_before: (H, W) float64 bilinear votes of the exposure's events where they were
            recorded; events_after: the same events carried to mid-exposure by the motion.
        exposure: the window, µs.
        contrast: the c settled for the exposure (the deconvolution's anchor is EDI's with it).
        notes: what the method said (fallbacks to EDI and why).
        fallback_contrast: the c of the EDI frames blended in, refitted to the deconvolution
            when ``contrast`` was estimated (:func:`~trmd_cli.deconv.fit_contrast`); None:
            ``contrast``.
    """

    motion: GlobalMotion
    displacement: np.ndarray
    weight: np.ndarray
    events_before: np.ndarray
    events_after: np.ndarray
    exposure: Exposure
    contrast: float
    notes: tuple[str, ...] = ()
    fallback_contrast: float | None = None


def displacement_field(motion, width: int, height: int) -> np.ndarray:
    """(H, W, 2) float32: where ``motion`` carries each pixel of the middle frame from the
    start of the exposure (u = 0) to its end (u = 1), pixels."""
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    x0, y0 = motion.positions(0.0, xs, ys)
    x1, y1 = motion.positions(1.0, xs, ys)
    return np.stack([x1 - x0, y1 - y0], axis=-1).astype(np.float32)


def motion_views(blurry: np.ndarray, events: EventStream, exposure: Exposure, *,
                 edi=None) -> MotionViews:
    """Estimate the exposure's motion and run the motion method's guard, as
    ``trmd deblur --method motion`` does.

    Args:
        blurry: (H, W[, 3]) float32 [0, 1]; events, exposure: the stream and its window (µs).
        edi: the :class:`~trmd_cli.methods.EdiMethod` that settles the exposure, as the
            run settled it: its c (given, the recording's — refitted for EDI's frames as ``trmd
            deblur`` does — or None: estimated on this frame alone), hot pixels, isolated
            events and the recording's fixed pattern (taken out of the frame first). None:
            ``EdiMethod(3)``.
    """
    from .edi import check_blurry
    from .methods import EdiMethod, deconv_noise, motion_frames, pattern_free
    from .motion.cmax import warped_image, window_points

    edi = EdiMethod(3) if edi is None else edi
    recorded = check_blurry(blurry, events.width, events.height)
    b = pattern_free(edi.pattern, recorded)
    noise = deconv_noise(recorded, b)
    prep = edi.prepare(b, events, exposure)
    _, res = motion_frames(b, events, exposure, np.array([0.5]), prep, noise=noise)
    w, h = events.width, events.height
    x, y, u = window_points(events, exposure, prep.hot)
    before = warped_image(GlobalMotion(), x, y, u, w, h)
    after = warped_image(res.motion, x, y, u, w, h)
    return MotionViews(res.motion, displacement_field(res.motion, w, h),
                       np.asarray(res.weight, np.float32), before, after, exposure,
                       float(prep.contrast), tuple(res.notes), res.fallback_contrast)


def _r(v: float, digits: int = 4) -> float:
    return round(float(v), digits)


def motion_summary(views: MotionViews) -> dict[str, Any]:
    """motion.json: the motion's parameters with their units, and what became of it."""
    from .deconv import MIN_GAIN

    m, e = views.motion, views.exposure
    h, w = views.weight.shape
    per_s = 1e6 / e.duration_us
    disp = np.hypot(views.displacement[..., 0], views.displacement[..., 1])
    vx, vy = m.velocity
    return {
        "exposure_us": [int(e.start_us), int(e.end_us)],
        "exposure_duration_us": int(e.duration_us),
        "time": "u: fraction of the exposure (0 = start, 1 = end); the model is centred on "
                "mid-exposure, tau = u - 0.5",
        "model": "p(tau) = c + exp(zoom*tau) R(rotation*tau) h(p0 - c) + velocity*tau "
                 "+ acceleration*tau^2/2 + jerk*tau^3/6, h(r) = r / (1 + tau * perspective . r)",
        "velocity_px_per_exposure": [_r(vx), _r(vy)],
        "velocity_px_per_s": [_r(vx * per_s, 2), _r(vy * per_s, 2)],
        "direction_deg": _r(math.degrees(math.atan2(vy, vx)) % 360.0, 2),
        "direction": "angle of the velocity from +x (right) towards +y (down), degrees",
        "acceleration_px_per_exposure2": [_r(m.acceleration[0]), _r(m.acceleration[1])],
        "jerk_px_per_exposure3": [_r(m.jerk[0]), _r(m.jerk[1])],
        "rotation_rad_per_exposure": _r(m.rotation, 6),
        "rotation_deg_per_exposure": _r(math.degrees(m.rotation), 4),
        "zoom_log_scale_per_exposure": _r(m.zoom, 6),
        "perspective_per_px_per_exposure": [float(f"{m.perspective[0]:.4g}"),
                                            float(f"{m.perspective[1]:.4g}")],
        "centre_px": [_r(m.centre[0], 2), _r(m.centre[1], 2)],
        "max_displacement_from_middle_px": _r(m.max_displacement_px(w, h), 3),
        "start_to_end_px": {"mean": _r(float(disp.mean()), 3),
                            "max": _r(float(disp.max(initial=0.0)), 3)},
        "start_to_end_meaning": "length of each pixel's displacement from the start of the "
                                "exposure to its end (what flow.png shows)",
        "motion_found": bool(m.confidence >= MIN_GAIN),
        "motion_found_meaning": "the events show a clear global motion (confidence ≥ "
                                f"{MIN_GAIN}); if not, the parameters above are only the "
                                "search's best candidate, and EDI's frames are used",
        "confidence": _r(m.confidence),
        "confidence_meaning": "contrast gain of the events carried by the motion over the "
                              "events as recorded (1 = the events show no motion; the "
                              "deconvolution is trusted fully from 1.1, never below 1.05)",
        "events": int(m.events),
        "deconvolution_share": _r(float(views.weight.mean())),
        "deconvolution_share_meaning": "mean of weight.png: the deconvolution's share in the "
                                       "output, the rest EDI's",
        "contrast": _r(views.contrast),
        "fallback_contrast": None if views.fallback_contrast is None else
        _r(views.fallback_contrast),
        "fallback_contrast_meaning": "c of EDI's frames where the deconvolution is not kept: "
                                     "the estimated c refitted to the deconvolution's change "
                                     "of log intensity against the events' count (null: "
                                     "contrast, given or no fit)",
        "notes": list(views.notes),
    }
