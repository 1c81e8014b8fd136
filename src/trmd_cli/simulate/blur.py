"""From a stream of sharp sub-step frames to events, blurry frames and latent ground truth.

Blur model. The blurry frame of an exposure ``[t0, t1]`` is the time average of the sharp
frames over it, integrated with the trapezoid rule over the sub-steps — the exact integral of
the piecewise-linear sequence the event sensor also sees. Pixel values are treated as *linear*
intensity, including 8-bit images of ordinary photos and videos (which are gamma-encoded): the
GoPro-based event datasets do the same, and EDI/TRMD assume ``B = mean(L)``. Optional Gaussian
read noise (σ in [0, 1] units) is added to the blurry frame, then clipped to [0, 1].

Ground truth is the 2N+1 sharp frames at ``t0 + k·T/(2N)`` (rounded to µs), which must be
sub-steps of the sequence: :func:`uniform_grid` and the scenes put them there.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..events import EventStream, Exposure
from .sensor import EventSensor

__all__ = ["ExposureResult", "latent_times", "uniform_grid", "steps_for_motion",
           "run_exposures", "grid_blocks", "aps_pattern"]


def aps_pattern(rng: np.random.Generator, width: int, height: int, pixel_sigma: float = 0.012,
                column_sigma: float = 0.006) -> np.ndarray:
    """An APS sensor's fixed pattern, to add to every blurry frame of one sensor: each pixel's
    offset (σ = ``pixel_sigma``) and each column's (σ = ``column_sigma``), intensity in [0, 1]
    units; (H, W) float32. The defaults are about esl-cups' (2.4 grey levels of 255 found,
    :mod:`trmd_cli.fixed_pattern`)."""
    return (rng.normal(0, pixel_sigma, (height, width))
            + rng.normal(0, column_sigma, (1, width))).astype(np.float32)


@dataclass(frozen=True, eq=False)
class ExposureResult:
    """One finished exposure.

    Attributes:
        index: position in the list of exposures given to :func:`run_exposures`.
        exposure: its window, µs.
        blurry: (H, W) float32, mean of the sub-steps (+ read noise), [0, 1].
        sharp: (2N+1, H, W) float32 latent frames at ``t0 + k·T/(2N)``.
        motion: (J, 3, 3) float64 true camera path over the exposure (middle-frame pixels →
            pixels at exposure fraction ``j/(J−1)``; see
            :meth:`~trmd_cli.simulate.trajectory.StillScene.exposure_motion`), or None when
            the scene has no camera path (videos).
    """

    index: int
    exposure: Exposure
    blurry: np.ndarray
    sharp: np.ndarray
    motion: np.ndarray | None = None


def latent_times(exposure: Exposure, n: int) -> np.ndarray:
    """The 2N+1 latent instants ``t0 + k·T/(2N)`` rounded to integer µs: (2N+1,) int64."""
    return np.rint(exposure.instants_us(n)).astype(np.int64)


def steps_for_motion(motion_px: float, n: int, max_px_per_step: float = 1.0) -> int:
    """Sub-steps per exposure so that ``motion_px`` of motion moves ≤ ``max_px_per_step`` per
    step; a multiple of 2N so the latent instants are sub-steps."""
    if max_px_per_step <= 0:
        raise InputError(f"max_px_per_step must be positive, got {max_px_per_step}")
    s = max(1, int(math.ceil(motion_px / max_px_per_step - 1e-9)))
    return int(math.ceil(s / (2 * n)) * 2 * n)


def uniform_grid(exposures: list[Exposure], n: int, steps_per_exposure: int,
                 start_us: int | None = None, end_us: int | None = None) -> np.ndarray:
    """Sample times (int64 µs, strictly increasing) covering ``[start_us, end_us]``.

    Each exposure gets ``steps_per_exposure`` equal steps (a multiple of 2N, so its latent
    instants are on the grid); the time between exposures gets steps no longer than those.

    Raises:
        InputError: steps shorter than 1 µs (exposure too short for that much motion).
    """
    if steps_per_exposure % (2 * n):
        raise InputError(f"steps per exposure ({steps_per_exposure}) must be a multiple of 2N")
    exps = sorted(exposures, key=lambda e: e.start_us)
    lo = exps[0].start_us if start_us is None else int(start_us)
    hi = exps[-1].end_us if end_us is None else int(end_us)
    step = min(e.duration_us for e in exps) / steps_per_exposure
    if step < 1.0:
        raise InputError(
            f"{steps_per_exposure} sub-steps do not fit in a {min(e.duration_us for e in exps)}"
            " µs exposure (steps must be ≥ 1 µs)",
            hint="use a longer `exposure_us` or less motion")
    parts = []
    cursor = lo
    for e in exps:
        if e.start_us > cursor:
            k = max(1, int(math.ceil((e.start_us - cursor) / step)))
            parts.append(np.rint(np.linspace(cursor, e.start_us, k + 1)[:-1]))
        parts.append(np.rint(e.start_us + np.arange(steps_per_exposure)
                             * (e.duration_us / steps_per_exposure)))
        parts.append(latent_times(e, n).astype(np.float64))
        cursor = max(cursor, e.end_us)
    if hi > cursor:
        k = max(1, int(math.ceil((hi - cursor) / step)))
        parts.append(np.rint(np.linspace(cursor, hi, k + 1)))
    else:
        parts.append(np.array([float(cursor)]))
    grid = np.unique(np.concatenate(parts).astype(np.int64))
    return grid[(grid >= lo) & (grid <= hi)]


def grid_blocks(grid_us: np.ndarray, render: Callable[[np.ndarray], np.ndarray],
                block: int = 32) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Render a fixed grid in blocks: yields (times (b,), frames (b, H, W))."""
    for i in range(0, len(grid_us), block):
        t = grid_us[i:i + block]
        yield t, render(t)


class _Accumulator:
    """Trapezoid integral and latent captures of one exposure."""

    def __init__(self, index: int, exposure: Exposure, n: int, shape: tuple[int, int]):
        self.index, self.exposure = index, exposure
        self.acc = np.zeros(shape, np.float64)
        self.latent = latent_times(exposure, n)
        self.sharp = np.full((2 * n + 1, *shape), np.nan, np.float32)
        self.captured = np.zeros(2 * n + 1, bool)

    def add(self, t: np.ndarray, frames: np.ndarray) -> None:
        """``t`` (m,) and ``frames`` (m, H, W) include the previous block's last sample first."""
        e = self.exposure
        dt = np.diff(t).astype(np.float64)
        inside = (t[:-1] >= e.start_us) & (t[1:] <= e.end_us)
        if inside.any():
            w = np.zeros(len(t))
            w[:-1] += np.where(inside, 0.5 * dt, 0.0)
            w[1:] += np.where(inside, 0.5 * dt, 0.0)
            nz = np.flatnonzero(w)
            sel = np.asarray(frames[nz], np.float32).reshape(len(nz), -1)
            self.acc += (w[nz].astype(np.float32) @ sel).reshape(self.acc.shape)
        pos = np.searchsorted(t, self.latent)
        hit = (pos < len(t)) & (t[np.minimum(pos, len(t) - 1)] == self.latent)
        for k in np.flatnonzero(hit & ~self.captured):
            self.sharp[k] = frames[pos[k]]
            self.captured[k] = True

    def result(self, read_noise: float, rng: np.random.Generator | None) -> ExposureResult:
        if not self.captured.all():
            missing = self.latent[~self.captured].tolist()
            raise InputError(f"latent instants {missing} µs are not sub-steps of the sequence",
                             hint="this is a bug in the scene's time grid; please report it")
        blurry = (self.acc / self.exposure.duration_us).astype(np.float32)
        if read_noise > 0:
            if rng is None:
                raise InputError("read noise needs a random generator")
            blurry = blurry + rng.normal(0.0, read_noise, blurry.shape).astype(np.float32)
        np.clip(blurry, 0.0, 1.0, out=blurry)
        return ExposureResult(self.index, self.exposure, blurry, self.sharp)


def run_exposures(blocks: Iterable[tuple[np.ndarray, np.ndarray]], exposures: list[Exposure],
                  n: int, sensor: EventSensor, *, read_noise: float = 0.0,
                  noise_rng: np.random.Generator | None = None,
                  progress: Callable[[int], None] | None = None,
                  ) -> Iterator[EventStream | ExposureResult]:
    """Feed sharp sub-steps to ``sensor`` and integrate exposures, in one pass.

    Args:
        blocks: (times (b,) int64 µs, frames (b, H, W) linear [0, 1]) in time order; every
            exposure's start, end and latent instants must be among the times.
        exposures: windows to integrate (any order; results come when each one ends).
        n: latent frames 2N+1 per exposure.
        sensor: fed every sample; its first sample sets its state.
        read_noise: σ of Gaussian noise added to each blurry frame.
        progress: called with the time (µs) reached after each block.

    Yields:
        :class:`EventStream` blocks (time order) and :class:`ExposureResult` as each exposure
        completes (an exposure is complete once a sample at or after its end was seen).
    """
    h, w = sensor.height, sensor.width
    pending = sorted(range(len(exposures)), key=lambda i: exposures[i].start_us)
    active: list[_Accumulator] = []
    prev_t: np.ndarray | None = None
    prev_f: np.ndarray | None = None
    for t, frames in blocks:
        t = np.asarray(t, np.int64)
        if len(t) == 0:
            continue
        ev = sensor.feed(frames, t)
        if len(ev):
            yield ev
        while pending and exposures[pending[0]].start_us <= t[-1]:
            i = pending.pop(0)
            active.append(_Accumulator(i, exposures[i], n, (h, w)))
        if active:
            tt = t if prev_t is None else np.concatenate([prev_t, t])
            ff = frames if prev_f is None else np.concatenate([prev_f, frames])
            for acc in active:
                acc.add(tt, ff)
            done = [a for a in active if a.exposure.end_us <= t[-1]]
            for a in done:
                active.remove(a)
                yield a.result(read_noise, noise_rng)
        prev_t, prev_f = t[-1:], np.asarray(frames[-1:])
        if progress is not None:
            progress(int(t[-1]))
