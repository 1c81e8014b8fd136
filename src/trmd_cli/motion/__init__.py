"""Motion over one exposure from its events: a global parametric model
(:class:`GlobalMotion`) estimated by contrast maximisation (:func:`estimate_motion`); or a
motion known from elsewhere as sampled homographies (:class:`SampledMotion`, the simulator's
true camera path)."""

from __future__ import annotations

from .cmax import MIN_EVENTS, MotionSearch, estimate_motion, split_agreement, warped_image
from .model import GlobalMotion
from .sampled import SampledMotion, event_gain

__all__ = ["GlobalMotion", "MotionSearch", "estimate_motion", "split_agreement", "warped_image",
           "MIN_EVENTS", "SampledMotion", "event_gain"]
