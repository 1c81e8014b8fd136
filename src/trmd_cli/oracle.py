"""The motion method with the motion given instead of estimated: on simulated data, the true
camera path (``frames/motion``), so ``trmd eval`` can tell how much of the motion method's
error is the estimated motion's.

:class:`TruePathMethod` is :class:`~trmd_cli.methods.MotionMethod` built with the path:
the same deconvolution, the same guard against EDI and the same fallbacks
(:func:`~trmd_cli.deconv.motion_deblur` with ``motion=``). The guard judges the given motion as
it judges an estimate — its contrast gain on the events (:func:`~trmd_cli.motion.event_gain`),
per tile and overall — so the only difference between the two rows of an evaluation is the motion.
"""

from __future__ import annotations

from .errors import InputError
from .methods import DEFAULT_N, Estimate, MotionMethod
from .motion.sampled import SampledMotion

__all__ = ["TruePathMethod", "TRUE_PATH"]

#: the evaluation name of the motion method along the true camera path
TRUE_PATH = "motion-true-path"


class TruePathMethod(MotionMethod):
    """``--method motion`` with the exposure's true camera path in place of the estimate
    (evaluation only: a path is known for simulated data alone). c is settled as EDI settles it,
    for the fallback, exactly as :class:`~trmd_cli.methods.MotionMethod` does.

    Args:
        n: 2N+1 latent frames.
        motion: the exposure's true path.
        contrast: c for EDI (None = estimated per frame).
    """

    name = TRUE_PATH
    # said beside the estimated motion's own notes: say which of the two it is
    note_prefix = "along the true camera path: "
    summary = ("the motion method along the simulator's true camera path instead of the motion "
               "estimated from the events (simulated data only): the ceiling of a perfect "
               "motion estimate")

    def __init__(self, n: int = DEFAULT_N, motion: SampledMotion | None = None,
                 contrast: float | None = None, hot_pixels: bool = True, *,
                 drop_isolated: bool = True) -> None:
        if motion is None:
            raise InputError("the true-path method needs a camera path",
                             hint="evaluate a set made by `trmd simulate` from a still image")
        super().__init__(n, contrast, hot_pixels, motion, drop_isolated=drop_isolated)

    @classmethod
    def from_config(cls, config) -> TruePathMethod:
        raise InputError(f"`{TRUE_PATH}` is built per frame with that frame's path",
                         hint="`trmd eval` builds it from the set's frames/motion")

    def from_bins(self, blurry, bins, fractions=None) -> Estimate:
        raise InputError(f"`{TRUE_PATH}` needs event times; binned events have none",
                         hint="evaluate a set with raw events (`trmd simulate` writes them)")
