"""Synthetic event data: a level-crossing event sensor, sharp sequences from stills and videos,
blur, and training datasets.

Light at import (numpy only); OpenCV is imported when frames are rendered, torch only by
:mod:`trmd_cli.simulate.dataset`.
"""

from __future__ import annotations

from .blur import ExposureResult, aps_pattern, latent_times, run_exposures, uniform_grid
from .sample import (
    DEFAULT_EXPOSURE_US,
    Sample,
    SequencePlan,
    SimulatedSequence,
    iter_sequence,
    make_sample,
    make_sequence,
    plan_exposures,
    plan_sequence,
)
from .sensor import EventSensor, SensorConfig, simulate_events
from .trajectory import MotionRanges, to_gray

__all__ = [
    "SensorConfig",
    "EventSensor",
    "simulate_events",
    "MotionRanges",
    "Sample",
    "SimulatedSequence",
    "make_sample",
    "make_sequence",
    "iter_sequence",
    "plan_sequence",
    "SequencePlan",
    "plan_exposures",
    "ExposureResult",
    "aps_pattern",
    "run_exposures",
    "uniform_grid",
    "latent_times",
    "to_gray",
    "DEFAULT_EXPOSURE_US",
]
