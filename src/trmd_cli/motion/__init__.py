"""Motion over one exposure from its events: a global parametric model
(:class:`GlobalMotion`) estimated by contrast maximisation (:func:`estimate_motion`)."""

from __future__ import annotations

from .cmax import MIN_EVENTS, MotionSearch, estimate_motion, warped_image
from .model import GlobalMotion

__all__ = ["GlobalMotion", "MotionSearch", "estimate_motion", "warped_image", "MIN_EVENTS"]
