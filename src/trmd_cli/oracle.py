"""The motion method with the motion given instead of estimated: on simulated data, the true
camera path (``frames/motion``), so ``trmd eval`` can tell how much of the motion method's
error is the estimated motion's.

:func:`deblur_along` is :func:`trmd_cli.deconv.motion_deblur` after its estimate: the same
deconvolution, the same guard against EDI and the same fallbacks, from the same public pieces
(:func:`~trmd_cli.deconv.deconvolve`, :func:`~trmd_cli.deconv.tile_gains`,
:func:`~trmd_cli.deconv.guard_weights`). The guard judges the given motion as it judges an
estimate — its contrast gain on the events (:func:`~trmd_cli.motion.event_gain`), per tile and
overall — so the only difference between the two rows of an evaluation is the motion.
"""

from __future__ import annotations

import numpy as np

from .edi import check_blurry
from .errors import InputError
from .methods import DEFAULT_N, EdiMethod, Estimate, MethodNeeds, Prepared
from .motion.sampled import SampledMotion

__all__ = ["deblur_along", "TruePathMethod", "TRUE_PATH"]

#: the evaluation name of the motion method along the true camera path
TRUE_PATH = "motion-true-path"


def deblur_along(blurry: np.ndarray, events, exposure, fractions, edi_frames: np.ndarray,
                 edi_middle: np.ndarray, motion, hot_mask: np.ndarray | None = None,
                 config=None):
    """Deconvolve ``blurry`` along a given ``motion`` and blend with EDI per tile.

    Args:
        blurry: (H, W[, 3]) float32 [0, 1]; events, exposure: the window's events (µs).
        fractions: (K,) exposure fractions of the wanted frames.
        edi_frames: (K, H, W[, 3]) EDI's frames at ``fractions`` (the fallback).
        edi_middle: (H, W[, 3]) EDI's middle frame (the solver's first guess).
        motion: a :class:`~trmd_cli.motion.SampledMotion` (its confidence is measured here on
            the events) or a :class:`~trmd_cli.motion.GlobalMotion` (used as it is).
        hot_mask: (H, W) bool pixels whose events are ignored.
        config: :class:`~trmd_cli.deconv.DeconvConfig` (default settings when None).
    Returns:
        :class:`~trmd_cli.deconv.MotionDeblur` with ``motion`` the motion used.
    """
    from .deconv import motion_deblur

    if isinstance(motion, SampledMotion):
        motion = motion.with_evidence(events, exposure, hot_mask)
    return motion_deblur(blurry, events, exposure, fractions, edi_frames, edi_middle, hot_mask,
                         config, motion=motion)


class TruePathMethod:
    """``--method motion`` with the exposure's true camera path in place of the estimate
    (evaluation only: a path is known for simulated data alone). c is settled as EDI settles it,
    for the fallback, exactly as :class:`~trmd_cli.methods.MotionMethod` does.

    Args:
        n: 2N+1 latent frames.
        motion: the exposure's true path.
        contrast: c for EDI (None = estimated per frame).
    """

    name = TRUE_PATH
    needs = MethodNeeds(contrast=True)
    weights_hash = None
    precision = None
    summary = ("the motion method along the simulator's true camera path instead of the motion "
               "estimated from the events (simulated data only): the ceiling of a perfect "
               "motion estimate")

    def __init__(self, n: int = DEFAULT_N, motion: SampledMotion | None = None,
                 contrast: float | None = None, hot_pixels: bool = True) -> None:
        if motion is None:
            raise InputError("the true-path method needs a camera path",
                             hint="evaluate a set made by `trmd simulate` from a still image")
        self.n = n
        self.motion = motion
        self._edi = EdiMethod(n, contrast, hot_pixels)

    def prepare(self, blurry, events, exposure=None) -> Prepared:
        """c settled as EDI settles it (see :meth:`EdiMethod.prepare`)."""
        return self._edi.prepare(blurry, events, exposure)

    def __call__(self, blurry, events, exposure, instants_us=None) -> Estimate:
        b = check_blurry(blurry, events.width, events.height)
        inst = exposure.instants_us(self.n) if instants_us is None else \
            np.asarray(instants_us, np.float64)
        prep = self.prepare(b, events, exposure)
        fr = (inst - exposure.start_us) / exposure.duration_us
        lat = prep.model.latent(b, np.append(fr, 0.5), prep.contrast)
        res = deblur_along(b, events, exposure, fr, lat[:-1], lat[-1], self.motion, prep.hot)
        # said beside the estimated motion's own notes: say which of the two it is
        notes = tuple(f"along the true camera path: {note}" for note in res.notes)
        return Estimate(res.frames, inst, prep.contrast, prep.estimated, prep.reliable,
                        prep.hot_pixels, prep.note, notes)

    def from_bins(self, blurry, bins, fractions=None) -> Estimate:
        raise InputError(f"`{TRUE_PATH}` needs event times; binned events have none",
                         hint="evaluate a set with raw events (`trmd simulate` writes them)")
