"""Synthetic samples from a still image: blurry frame(s), their events, and sharp ground truth.

One call draws a random view of the image, a smooth camera path (and optional foreground
layers), samples it finely enough that nothing moves more than ``max_px_per_step`` pixels per
sub-step, runs the event sensor over the sub-steps and averages them over each exposure.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError
from ..events import EventStream, Exposure
from .blur import ExposureResult, grid_blocks, run_exposures, steps_for_motion, uniform_grid
from .sensor import EventSensor, SensorConfig
from .trajectory import MotionRanges, StillScene, make_scene

__all__ = ["Sample", "SimulatedSequence", "SequencePlan", "make_sample", "make_sequence",
           "iter_sequence", "plan_sequence", "plan_exposures", "DEFAULT_EXPOSURE_US",
           "MOTION_SAMPLES"]

#: default exposure of a simulated frame, µs
DEFAULT_EXPOSURE_US = 20_000
#: instants per exposure at which the true camera path is recorded (fractions j/32): the
#: path's knots are half an exposure apart, so straight lines between these bend it by
#: ≈ 0.01 px even at the training set's largest motion
MOTION_SAMPLES = 33


@dataclass(frozen=True, eq=False)
class Sample:
    """One simulated exposure.

    Attributes:
        blurry: (H, W) float32 [0, 1], mean of the sub-steps over the exposure.
        sharp: (2N+1, H, W) float32 latent frames at ``k·T/(2N)``.
        events: the exposure's events, times in ``[exposure.start_us, exposure.end_us]``.
        exposure: the window (starts at 0 for :func:`make_sample`).
        contrast: mean true contrast threshold of the sensor (ON and OFF, all pixels).
        motion: (J, 3, 3) float64 true camera path: middle-frame pixels → pixels at exposure
            fraction ``j/(J−1)`` (:class:`~trmd_cli.motion.SampledMotion` reads it).
    """

    blurry: np.ndarray
    sharp: np.ndarray
    events: EventStream
    exposure: Exposure
    contrast: float
    motion: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class SimulatedSequence:
    """Consecutive exposures along one camera path.

    Attributes:
        blurry: (K, H, W) float32; sharp: (K, 2N+1, H, W) float32.
        exposures: K windows, µs. events: all events of the span (gaps included).
        contrast: mean true contrast threshold.
        motion: (K, J, 3, 3) float64 true camera path of each exposure (see
            :class:`Sample`).
    """

    blurry: np.ndarray
    sharp: np.ndarray
    exposures: list[Exposure]
    events: EventStream
    contrast: float
    motion: np.ndarray | None = None


def plan_exposures(frames: int, exposure_us: int, interval_us: int | None,
                   t0_us: int = 0) -> list[Exposure]:
    """``frames`` windows of ``exposure_us`` starting every ``interval_us`` (default: 1.2 ×
    the exposure, i.e. gaps of a fifth of the exposure, close to a DAVIS346 at 8 fps)."""
    if frames < 1:
        raise InputError(f"`frames` must be ≥ 1, got {frames}")
    if exposure_us < 2:
        raise InputError(f"exposure of {exposure_us} µs is too short")
    interval = int(round(1.2 * exposure_us)) if interval_us is None else int(interval_us)
    if frames > 1 and interval < exposure_us:
        raise InputError(f"frame interval {interval} µs is shorter than the exposure "
                         f"{exposure_us} µs", hint="raise `interval_us`")
    return [Exposure(t0_us + k * interval, t0_us + k * interval + exposure_us)
            for k in range(frames)]


def _children(rng: np.random.Generator, k: int) -> list[np.random.Generator]:
    return [np.random.default_rng(s) for s in rng.integers(0, 2**63 - 1, k)]


@dataclass(frozen=True, eq=False)
class SequencePlan:
    """What :func:`iter_sequence` will simulate: the scene, the exposures and the sub-step
    times (int64 µs), plus the generators for the sensor and the read noise."""

    scene: StillScene
    exposures: list[Exposure]
    grid_us: np.ndarray
    sensor_rng: np.random.Generator
    noise_rng: np.random.Generator


def plan_sequence(
    image: np.ndarray,
    *,
    n: int = 3,
    size: tuple[int, int] = (346, 260),
    exposure_us: int = DEFAULT_EXPOSURE_US,
    frames: int = 1,
    frame_interval_us: int | None = None,
    rng: np.random.Generator,
    motion: MotionRanges | None = None,
    max_px_per_step: float = 1.0,
    zoom: tuple[float, float] | None = (1.0, 1.0),
    random_view: bool = True,
    t0_us: int = 0,
) -> SequencePlan:
    """Draw the view and the camera path, and choose sub-steps so that no point of the image
    (corners, centre, foreground corners) moves more than ``max_px_per_step`` per step."""
    if n < 1:
        raise InputError(f"N must be ≥ 1, got {n}", hint="use --n 3 (7 latent frames)")
    motion = MotionRanges() if motion is None else motion
    exposures = plan_exposures(frames, int(exposure_us), frame_interval_us, t0_us)
    span = exposures[-1].end_us - exposures[0].start_us
    scene_rng, sensor_rng, noise_rng = _children(rng, 3)
    duration = span / exposure_us
    scene = make_scene(image, size, motion, exposure_us, duration, scene_rng,
                       random_view=random_view, zoom=zoom, t0_us=t0_us,
                       centre=0.5 if frames == 1 else None)
    # 5 % headroom: the speed is measured on a finite set of instants
    speed = scene.max_speed_px(0.0, duration)
    steps = steps_for_motion(speed * 1.05, n, max_px_per_step)
    grid = uniform_grid(exposures, n, steps)
    return SequencePlan(scene, exposures, grid, sensor_rng, noise_rng)


def iter_sequence(
    image: np.ndarray,
    *,
    n: int = 3,
    size: tuple[int, int] = (346, 260),
    exposure_us: int = DEFAULT_EXPOSURE_US,
    frames: int = 1,
    frame_interval_us: int | None = None,
    rng: np.random.Generator,
    sensor: SensorConfig | None = None,
    motion: MotionRanges | None = None,
    read_noise: float = 0.0,
    max_px_per_step: float = 1.0,
    zoom: tuple[float, float] | None = (1.0, 1.0),
    random_view: bool = True,
    t0_us: int = 0,
    progress: Callable[[int], None] | None = None,
) -> tuple[EventSensor, list[Exposure], Iterator[EventStream | ExposureResult]]:
    """Streaming form of :func:`make_sequence`: returns the sensor, the exposures and an
    iterator of event blocks and finished exposures (bounded memory for long sequences); each
    finished exposure carries its true camera path (``ExposureResult.motion``, at
    :data:`MOTION_SAMPLES` even fractions)."""
    plan = plan_sequence(image, n=n, size=size, exposure_us=exposure_us, frames=frames,
                         frame_interval_us=frame_interval_us, rng=rng, motion=motion,
                         max_px_per_step=max_px_per_step, zoom=zoom, random_view=random_view,
                         t0_us=t0_us)
    sensor_cfg = SensorConfig() if sensor is None else sensor
    ev_sensor = EventSensor(sensor_cfg, size[0], size[1], plan.sensor_rng)
    it = run_exposures(grid_blocks(plan.grid_us, plan.scene.render), plan.exposures, n,
                       ev_sensor, read_noise=read_noise, noise_rng=plan.noise_rng,
                       progress=progress)
    return ev_sensor, plan.exposures, _with_motion(it, plan.scene)


def _with_motion(items: Iterator[EventStream | ExposureResult], scene: StillScene
                 ) -> Iterator[EventStream | ExposureResult]:
    fractions = np.linspace(0.0, 1.0, MOTION_SAMPLES)
    for item in items:
        if isinstance(item, ExposureResult):
            e = item.exposure
            item = replace(item, motion=scene.exposure_motion(e.start_us, e.end_us, fractions))
        yield item


def make_sequence(image: np.ndarray, **kwargs) -> SimulatedSequence:
    """K consecutive exposures of one random camera path over ``image``.

    Takes the arguments of :func:`iter_sequence` (``frames``, ``frame_interval_us``, …).
    """
    ev_sensor, exposures, it = iter_sequence(image, **kwargs)
    n = kwargs.get("n", 3)
    w, h = kwargs.get("size", (346, 260))
    events: list[EventStream] = []
    blurry = np.zeros((len(exposures), h, w), np.float32)
    sharp = np.zeros((len(exposures), 2 * n + 1, h, w), np.float32)
    motion = np.zeros((len(exposures), MOTION_SAMPLES, 3, 3))
    for item in it:
        if isinstance(item, EventStream):
            events.append(item)
        else:
            blurry[item.index], sharp[item.index] = item.blurry, item.sharp
            motion[item.index] = item.motion
    stream = EventStream.concatenate(events) if events else EventStream.empty(w, h)
    return SimulatedSequence(blurry, sharp, exposures, stream, ev_sensor.mean_contrast, motion)


def make_sample(
    image: np.ndarray,
    *,
    n: int = 3,
    size: tuple[int, int] = (346, 260),
    exposure_us: int = DEFAULT_EXPOSURE_US,
    rng: np.random.Generator,
    sensor: SensorConfig | None = None,
    motion: MotionRanges | None = None,
    read_noise: float = 0.0,
    max_px_per_step: float = 1.0,
    zoom: tuple[float, float] | None = (1.0, 1.0),
    random_view: bool = True,
) -> Sample:
    """One blurry frame of ``image`` with its events and 2N+1 sharp frames.

    Args:
        image: (H, W) or (H, W, 3), float [0, 1] or uint8/uint16; treated as linear.
        n: 2N+1 latent frames.
        size: output (W, H).
        exposure_us: exposure length T, µs; the exposure is ``[0, T]``.
        rng: all randomness (view, path, sensor mismatch and noise, read noise).
        sensor: event sensor (default: DAVIS-like :class:`SensorConfig`).
        motion: motion ranges (default :class:`MotionRanges`).
        read_noise: σ of Gaussian noise on the blurry frame.
        max_px_per_step: largest image motion between sub-steps, px.
        zoom: range of source pixels per output pixel (None: fit the whole image).
        random_view: random placement of the view (else centred).
    """
    seq = make_sequence(image, n=n, size=size, exposure_us=exposure_us, frames=1, rng=rng,
                        sensor=sensor, motion=motion, read_noise=read_noise,
                        max_px_per_step=max_px_per_step, zoom=zoom, random_view=random_view)
    return Sample(seq.blurry[0], seq.sharp[0], seq.events, seq.exposures[0], seq.contrast,
                  seq.motion[0])
