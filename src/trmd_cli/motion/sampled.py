"""A motion over one exposure given as sampled homographies: the simulator's true camera path.

``H_j`` (3×3) maps a pixel of the middle frame (exposure fraction u = ½) to where that point is
at fraction ``u_j``, in output pixel coordinates (pixel centres at integers, as OpenCV and
:class:`~trmd_cli.deconv.BlurOperator` use them). Between the samples the matrices, normalised
to ``H[2, 2] = 1``, are interpolated linearly in ``u`` — with the simulator's J = 33 samples the
interpolated path is within about 0.01 px of the smooth one — and outside ``[u_0, u_{J−1}]``
the end segments are extended. :meth:`SampledMotion.to_middle` inverts the interpolated matrix
itself, so it is the exact inverse of :meth:`SampledMotion.positions`.

It answers the questions :class:`~trmd_cli.motion.GlobalMotion` answers, in the same units
(pixels, exposure fractions), so the deconvolution and its guard take either.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError

__all__ = ["SampledMotion", "event_gain"]


def _evenly(j: int) -> np.ndarray:
    return np.linspace(0.0, 1.0, j)


@dataclass(frozen=True, eq=False)
class SampledMotion:
    """Motion of the image over one exposure as J homographies (see the module docstring).

    Attributes:
        homographies: (J, 3, 3) float64, middle-frame pixels → pixels at ``fractions[j]``;
            stored normalised (``H[2, 2] = 1``) and read-only.
        fractions: (J,) strictly increasing exposure fractions of the samples (default:
            evenly spaced from 0 to 1, ends included).
        centre: (cx, cy) pixels, the sensor centre (what a zero motion turns about; kept so
            that callers that compare a motion with no motion about its centre can).
        confidence: contrast gain of the exposure's events warped by this motion over the
            unwarped ones (variance ratio of the images of warped events, as
            :class:`GlobalMotion` has it; 0 = not measured, see :meth:`with_evidence`).
        events: number of events the confidence was measured on.
    """

    homographies: np.ndarray
    fractions: np.ndarray | None = None
    centre: tuple[float, float] = (0.0, 0.0)
    confidence: float = 0.0
    events: int = 0

    def __post_init__(self) -> None:
        h = np.array(self.homographies, np.float64)
        if h.ndim != 3 or h.shape[1:] != (3, 3) or h.shape[0] < 2:
            raise InputError(f"a sampled motion needs (J ≥ 2, 3, 3) homographies, got shape "
                             f"{h.shape}", hint="store one 3×3 matrix per sampled instant")
        if not np.isfinite(h).all() or np.any(np.abs(h[:, 2, 2]) < 1e-12):
            raise InputError("the sampled motion holds non-finite or degenerate homographies",
                             hint="each matrix must be finite with H[2, 2] ≠ 0")
        h = h / h[:, 2:3, 2:3]
        f = _evenly(len(h)) if self.fractions is None else np.array(self.fractions, np.float64)
        if f.shape != (len(h),) or not np.isfinite(f).all() or np.any(np.diff(f) <= 0):
            raise InputError(f"the sampled motion's {f.size} fractions do not match its "
                             f"{len(h)} homographies or are not strictly increasing",
                             hint="give one increasing exposure fraction per matrix")
        for a in (h, f):
            a.setflags(write=False)
        object.__setattr__(self, "homographies", h)
        object.__setattr__(self, "fractions", f)

    @property
    def samples(self) -> int:
        """J, the number of sampled instants."""
        return len(self.homographies)

    def _at(self, mats: np.ndarray, fractions) -> np.ndarray:
        """The matrices interpolated at ``fractions``: (..., 3, 3) with ``...`` their shape."""
        u = np.asarray(fractions, np.float64)
        f = self.fractions
        i = np.clip(np.searchsorted(f, u, side="right") - 1, 0, len(f) - 2)
        w = (u - f[i]) / (f[i + 1] - f[i])
        return (1.0 - w)[..., None, None] * mats[i] + w[..., None, None] * mats[i + 1]

    @staticmethod
    def _apply(m: np.ndarray, x, y) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        den = m[..., 2, 0] * x + m[..., 2, 1] * y + m[..., 2, 2]
        return ((m[..., 0, 0] * x + m[..., 0, 1] * y + m[..., 0, 2]) / den,
                (m[..., 1, 0] * x + m[..., 1, 1] * y + m[..., 1, 2]) / den)

    def positions(self, fractions, x0, y0) -> tuple[np.ndarray, np.ndarray]:
        """Where the middle frame's points ``(x0, y0)`` (pixels) are at ``fractions`` of the
        exposure; all three broadcast together. Returns (x, y) pixels."""
        return self._apply(self._at(self.homographies, fractions), x0, y0)

    def to_middle(self, fractions, x, y) -> tuple[np.ndarray, np.ndarray]:
        """The inverse of :meth:`positions`: the middle-frame point seen at ``(x, y)``
        (pixels) at ``fractions`` of the exposure."""
        # the adjugate of the interpolated matrix is its inverse up to a scale, which the
        # projective division removes (and it needs no determinant)
        h = self._at(self.homographies, fractions)
        adj = np.stack([np.cross(h[..., 1, :], h[..., 2, :]),
                        np.cross(h[..., 2, :], h[..., 0, :]),
                        np.cross(h[..., 0, :], h[..., 1, :])], axis=-1)
        return self._apply(adj, x, y)

    def max_displacement_px(self, width: int, height: int, samples: int = 17) -> float:
        """The largest distance (pixels) any sensor corner or the centre travels from its
        middle-frame position during the exposure (at ``samples`` even instants and at every
        sampled one)."""
        u = np.union1d(np.linspace(0.0, 1.0, samples),
                       self.fractions[(self.fractions >= 0) & (self.fractions <= 1)])[:, None]
        xs = np.array([0.0, width - 1.0, 0.0, width - 1.0, (width - 1) / 2])[None]
        ys = np.array([0.0, 0.0, height - 1.0, height - 1.0, (height - 1) / 2])[None]
        x, y = self.positions(u, xs, ys)
        return float(np.sqrt((x - xs) ** 2 + (y - ys) ** 2).max())

    def end_point_error_px(self, other, width: int, height: int, samples: int = 9,
                           grid: int = 8) -> float:
        """Mean distance (pixels) between where the two motions (this and any object with
        ``positions``, e.g. a :class:`GlobalMotion`) put a grid of sensor points, averaged over
        ``samples`` instants of the exposure."""
        u = np.linspace(0.0, 1.0, samples)[:, None, None]
        gx, gy = np.meshgrid(np.linspace(0, width - 1, grid), np.linspace(0, height - 1, grid))
        x1, y1 = self.positions(u, gx[None], gy[None])
        x2, y2 = other.positions(u, gx[None], gy[None])
        return float(np.sqrt((x1 - x2) ** 2 + (y1 - y2) ** 2).mean())

    def with_evidence(self, events, exposure, hot_mask: np.ndarray | None = None
                      ) -> SampledMotion:
        """This motion with ``confidence`` and ``events`` measured on the exposure's events
        (see :func:`event_gain`)."""
        gain, n = event_gain(self, events, exposure, hot_mask)
        return replace(self, confidence=gain, events=n)


def event_gain(motion, events, exposure, hot_mask: np.ndarray | None = None
               ) -> tuple[float, int]:
    """How much ``motion`` sharpens the exposure's events: the variance of their image carried
    to the middle by it, over that of the events as recorded (both voted bilinearly and
    smoothed by a σ = 1 px Gaussian, as the confidence of an estimate is read). Returns (gain,
    events used); (0, n) with fewer than 2 events.

    Args:
        motion: anything with ``to_middle(fractions, x, y)`` (pixels, exposure fractions).
        events, exposure: the stream and its window (µs); events of ``hot_mask`` (H, W) bool
            pixels are left out.
    """
    from scipy.ndimage import gaussian_filter

    from .cmax import warped_image, window_points
    from .model import GlobalMotion

    x, y, u = window_points(events, exposure, hot_mask)
    if len(x) < 2:
        return 0.0, int(len(x))
    w, h = events.width, events.height

    def variance(m) -> float:
        img = warped_image(m, x, y, u, w, h)
        return float(gaussian_filter(img, 1.0, mode="constant").var())

    base = variance(GlobalMotion())
    gain = variance(motion) / base if base > 0 else 0.0
    return (gain if math.isfinite(gain) else 0.0), int(len(x))
