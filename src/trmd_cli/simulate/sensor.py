"""A level-crossing event camera (ESIM / v2e style), vectorised over pixels, streamable.

Model. Each pixel compares its log intensity ``L = log(I + eps)`` (``I`` linear, [0, 1]) with a
stored reference ``ref``. Between two input samples ``L`` is interpolated linearly in time, so
a pixel whose ``L`` moves by several thresholds within one step fires several events whose times
are solved exactly on that line. An ON event fires when ``L − ref`` reaches the pixel's
``c_on``; an OFF event when ``ref − L`` reaches ``c_off``. After an event:

- without a refractory period ``ref`` moves by exactly one threshold (ESIM);
- with a refractory period ``R`` the pixel is blind for ``R`` and its reference follows ``L``
  while blind (a real pixel is held in reset), so on a steady ramp of slope ``r`` events come
  every ``R + c/|r|`` instead of every ``c/|r|``.

Noise sources (all off in :meth:`SensorConfig.clean`):

- threshold mismatch: per-pixel ``c_on ~ N(contrast_on, σ)``, ``c_off ~ N(contrast_off, σ)``,
  clipped below at ``min_contrast``, drawn once per sensor;
- shot noise: a Poisson process per pixel, polarity ±1 with equal odds, rate
  ``shot_noise_hz × (1.75 − 1.5·I)`` (dark pixels are noisier, as in v2e; the factor is 1 at
  mid-grey). Shot events do not move the reference;
- leak: the reference drifts down by ``leak_hz · c_on`` per second, so a static pixel emits ON
  events at about ``leak_hz`` (per-pixel rate ``leak_hz × U(0.5, 1.5)``);
- hot pixels: a fraction of pixels that fire Poisson events at ``hot_pixel_hz``, each with a
  fixed polarity (ON with probability 3/4);
- random initial phase: the reference starts at a uniform random offset inside
  ``(L − c_on, L + c_off)`` rather than exactly at ``L`` — a real camera has been running before
  the recording starts.

Everything is drawn from the ``numpy.random.Generator`` given to the sensor, step by step, so a
sequence fed in chunks gives exactly the events of the same sequence fed at once.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from ..errors import InputError, check_shape
from ..events import EventStream

__all__ = ["SensorConfig", "EventSensor", "simulate_events"]

#: shot-noise rate factor at black (1.75) and white (0.25), linear in between
_SHOT_DARK, _SHOT_SLOPE = 1.75, 1.5
#: probability that a hot pixel fires ON (else OFF)
_HOT_ON_PROB = 0.75
#: samples converted to log at once inside ``feed`` (memory: _BLOCK × H × W × 8 bytes)
_BLOCK = 32


@dataclass(frozen=True)
class SensorConfig:
    """Parameters of the simulated event sensor. Defaults look like a DAVIS346 at default biases.

    How the defaults were chosen: EDI on real DAVIS346 frames (``shared/data/real/esl-cups``)
    works with c ≈ 0.3, v2e uses 0.2 and σ = 0.03; those recordings show about one hot pixel in
    90,000 firing ~30 Hz, and ~0.2 events/pixel/s in their quietest regions (shot noise + leak
    here: 0.15). With these defaults, blur like the real frames' gives event densities of the
    same order (see ``bench/bench_simulate.py``, section 4).

    Attributes:
        contrast_on: mean ON threshold in log intensity (natural log).
        contrast_off: mean OFF threshold (positive number).
        contrast_sigma: per-pixel standard deviation of both thresholds (mismatch).
        refractory_us: blind time after each signal event, µs (0 = none).
        shot_noise_hz: Poisson noise events per pixel per second (at mid-grey).
        leak_hz: leak (ON) events per pixel per second in a static scene.
        hot_pixel_fraction: fraction of pixels that are hot.
        hot_pixel_hz: event rate of a hot pixel, per second.
        eps: offset in ``log(I + eps)``; also sets how noisy dark regions get.
        random_phase: start each reference at a random offset instead of exactly at ``L``.
        min_contrast: lower clip of the per-pixel thresholds.
    """

    contrast_on: float = 0.25
    contrast_off: float = 0.25
    contrast_sigma: float = 0.03
    refractory_us: float = 100.0
    shot_noise_hz: float = 0.1
    leak_hz: float = 0.05
    hot_pixel_fraction: float = 2e-5
    hot_pixel_hz: float = 30.0
    eps: float = 0.01
    random_phase: bool = True
    min_contrast: float = 0.01

    def __post_init__(self) -> None:
        for name in ("contrast_on", "contrast_off", "eps", "min_contrast"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"sensor {name} must be positive, got {v}")
        for name in ("contrast_sigma", "refractory_us", "shot_noise_hz", "leak_hz",
                     "hot_pixel_hz"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise InputError(f"sensor {name} must be ≥ 0, got {v}")
        if not 0 <= self.hot_pixel_fraction <= 1:
            raise InputError(f"hot_pixel_fraction must be in [0, 1], got {self.hot_pixel_fraction}")

    @classmethod
    def clean(cls, contrast: float = 0.2, eps: float = 0.01) -> SensorConfig:
        """An ideal sensor: one threshold everywhere, no refractory period, no noise at all."""
        return cls(contrast_on=contrast, contrast_off=contrast, contrast_sigma=0.0,
                   refractory_us=0.0, shot_noise_hz=0.0, leak_hz=0.0, hot_pixel_fraction=0.0,
                   eps=eps, random_phase=False)

    @classmethod
    def davis(cls) -> SensorConfig:
        """The DAVIS346-like default (same as ``SensorConfig()``)."""
        return cls()

    @property
    def is_clean(self) -> bool:
        return (self.contrast_sigma == 0 and self.refractory_us == 0 and self.shot_noise_hz == 0
                and self.leak_hz == 0 and (self.hot_pixel_fraction == 0 or self.hot_pixel_hz == 0)
                and not self.random_phase)

    @property
    def mean_contrast(self) -> float:
        """Mean of the ON and OFF thresholds."""
        return 0.5 * (self.contrast_on + self.contrast_off)

    def with_contrast(self, contrast: float) -> SensorConfig:
        return replace(self, contrast_on=contrast, contrast_off=contrast)

    def to_dict(self) -> dict:
        return asdict(self)


class EventSensor:
    """Per-pixel state of a simulated event camera; feed it frames in time order.

    The first sample ever fed only sets the state; every later sample produces the events
    between it and the sample before (``feed`` may be called many times: results do not depend
    on how a sequence is cut into chunks).

    Args:
        config: sensor parameters.
        width, height: sensor size in pixels.
        rng: source of every random draw (thresholds now, noise later).

    Attributes:
        c_on, c_off: (H, W) float64 per-pixel thresholds.
        hot: (H, W) bool hot-pixel mask.
    """

    def __init__(self, config: SensorConfig, width: int, height: int,
                 rng: np.random.Generator):
        if width <= 0 or height <= 0:
            raise InputError(f"sensor size {width}x{height} is not positive")
        self.config = config
        self.width, self.height = int(width), int(height)
        self.rng = rng
        npix = self.width * self.height
        cfg = config
        if cfg.contrast_sigma > 0:
            c_on = rng.normal(cfg.contrast_on, cfg.contrast_sigma, npix)
            c_off = rng.normal(cfg.contrast_off, cfg.contrast_sigma, npix)
            np.maximum(c_on, cfg.min_contrast, out=c_on)
            np.maximum(c_off, cfg.min_contrast, out=c_off)
        else:
            c_on = np.full(npix, float(cfg.contrast_on))
            c_off = np.full(npix, float(cfg.contrast_off))
        self._c_on, self._c_off = c_on, c_off
        n_hot = int(round(cfg.hot_pixel_fraction * npix)) if cfg.hot_pixel_hz > 0 else 0
        self._hot_idx = np.sort(rng.choice(npix, n_hot, replace=False)) if n_hot else \
            np.zeros(0, np.int64)
        self._hot_pol = np.where(rng.random(n_hot) < _HOT_ON_PROB, 1, -1).astype(np.int8)
        # leak as a per-pixel downward drift of the reference, in log units per µs
        self._leak = (cfg.leak_hz * rng.uniform(0.5, 1.5, npix) * c_on * 1e-6
                      if cfg.leak_hz > 0 else None)
        self._ref: np.ndarray | None = None  # reference level (drift-free frame of reference)
        self._le: np.ndarray | None = None  # effective log level at the last sample
        self._t: int | None = None  # time of the last sample, µs
        self._t_origin = 0
        self._blind_until = np.full(npix, -np.inf)
        self._blind_idx = np.zeros(0, np.int64)

    @property
    def c_on(self) -> np.ndarray:
        return self._c_on.reshape(self.height, self.width)

    @property
    def c_off(self) -> np.ndarray:
        return self._c_off.reshape(self.height, self.width)

    @property
    def hot(self) -> np.ndarray:
        m = np.zeros(self.width * self.height, bool)
        m[self._hot_idx] = True
        return m.reshape(self.height, self.width)

    @property
    def mean_contrast(self) -> float:
        """Mean true threshold over pixels and both polarities."""
        return float(0.5 * (self._c_on.mean() + self._c_off.mean()))

    @property
    def last_time_us(self) -> int | None:
        return self._t

    def _log(self, frames: np.ndarray) -> np.ndarray:
        """log(I + eps): (S, npix) float32 (3× faster than float64; its ~1e-7 error is far
        below any threshold — the per-pixel state is float64)."""
        x = frames.reshape(len(frames), -1).astype(np.float32) + np.float32(self.config.eps)
        return np.log(x, out=x)

    def _effective(self, log32: np.ndarray, t: int) -> np.ndarray:
        """Effective level (npix,) float64: log plus the leak drift at time ``t``."""
        le = log32.astype(np.float64)
        if self._leak is not None:
            le += float(t - self._t_origin) * self._leak
        return le

    def feed(self, frames: np.ndarray, times_us: np.ndarray) -> EventStream:
        """Feed samples ``frames`` (S, H, W) linear [0, 1] at ``times_us`` (S,) int64.

        Returns the events since the previous sample (sorted by time, int64 µs). Times must
        increase strictly, also across calls.

        Raises:
            ShapeError: frames not (S, H, W) of this sensor's size.
            InputError: times not strictly increasing, or not finite.
        """
        frames = np.asarray(frames)
        check_shape(frames, (None, self.height, self.width), "frames")
        times = np.asarray(times_us)
        if times.dtype.kind not in "iu":
            raise InputError(f"sample times must be integer µs, got {times.dtype}")
        times = times.astype(np.int64)
        if times.shape != (len(frames),):
            raise InputError(f"{len(frames)} frames but {times.shape} times")
        if len(times) == 0:
            return EventStream.empty(self.width, self.height)
        if (np.diff(times) <= 0).any() or (self._t is not None and times[0] <= self._t):
            raise InputError("sample times must increase strictly (at least 1 µs apart)",
                             hint="use fewer sub-steps or a longer exposure")
        if self._t is None:
            self._t_origin = int(times[0])
        parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        for b0 in range(0, len(times), _BLOCK):  # bounded memory for long inputs
            log32 = self._log(frames[b0:b0 + _BLOCK])
            for s in range(len(log32)):
                t = int(times[b0 + s])
                if self._le is None:
                    self._init_state(self._effective(log32[s], t), t)
                else:
                    self._step(self._effective(log32[s], t), t, frames[b0 + s], parts)
        if not parts:
            return EventStream.empty(self.width, self.height)
        idx = np.concatenate([p[0] for p in parts])
        t = np.concatenate([p[1] for p in parts])
        pol = np.concatenate([p[2] for p in parts])
        order = np.argsort(t, kind="stable")
        idx, t, pol = idx[order], t[order], pol[order]
        return EventStream((idx % self.width).astype(np.uint16),
                           (idx // self.width).astype(np.uint16), t, pol,
                           self.width, self.height)

    def _init_state(self, le0: np.ndarray, t0: int) -> None:
        ref = le0.copy()
        if self.config.random_phase:
            # L − ref uniform in (−c_off, c_on): the state of a pixel that has been running
            ref -= self.rng.uniform(0.0, 1.0, le0.shape) * (self._c_on + self._c_off) \
                - self._c_off
        self._ref, self._le, self._t = ref, le0, int(t0)

    def _step(self, le1: np.ndarray, t1: int, frame1: np.ndarray,
              parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> None:
        cfg = self.config
        ref, le0, t0 = self._ref, self._le, self._t
        dt = float(t1 - t0)
        refr = float(cfg.refractory_us)

        # pixels still blind from earlier events: the reference follows L while blind
        if len(self._blind_idx):
            b = self._blind_idx
            bu = self._blind_until[b]
            ended = bu < t1
            ref[b[~ended]] = le1[b[~ended]]
            be = b[ended]
            ref[be] = le0[be] + (le1[be] - le0[be]) * ((bu[ended] - t0) / dt)
            self._blind_idx = b[~ended]

        d1 = le1 - ref
        idx = np.flatnonzero((d1 >= self._c_on) | (d1 <= -self._c_off))
        if len(idx):
            up = d1[idx] > 0
            s = np.where(up, 1.0, -1.0)
            c = np.where(up, self._c_on[idx], self._c_off[idx])
            l0, l1, rf = le0[idx], le1[idx], ref[idx]
            # log units per µs; > 0 for every firing pixel, guarded against rounding
            rate = np.maximum(np.abs(l1 - l0) / dt, 1e-300)
            ts = np.maximum(float(t0), self._blind_until[idx])
            d_ts = l0 + (l1 - l0) * ((ts - t0) / dt) - rf  # L − ref at the start of sensitivity
            step_c = c + rate * refr  # reference move per event (= c without refractory)
            n = np.floor((s * d1[idx] - c) / step_c).astype(np.int64) + 1
            np.maximum(n, 1, out=n)
            t_first = ts + (c - s * d_ts) / rate
            period = step_c / rate
            total = int(n.sum())
            rep = np.repeat(np.arange(len(idx)), n)
            j = np.arange(total) - np.repeat(np.cumsum(n) - n, n)
            t_ev = t_first[rep] + j * period[rep]
            np.clip(t_ev, t0, t1, out=t_ev)
            parts.append((idx[rep], np.rint(t_ev).astype(np.int64),
                          np.where(up, 1, -1).astype(np.int8)[rep]))
            if refr > 0:
                bu = t_first + (n - 1) * period + refr
                self._blind_until[idx] = bu
                still = bu >= t1
                ref[idx[still]] = l1[still]
                ok = ~still
                ref[idx[ok]] = l0[ok] + (l1[ok] - l0[ok]) * ((bu[ok] - t0) / dt)
                if still.any():
                    # disjoint: pixels still blind from before cannot have fired
                    self._blind_idx = np.concatenate([self._blind_idx, idx[still]])
            else:
                ref[idx] = rf + s * n * c

        self._noise(t0, t1, frame1, parts)
        self._le, self._t = le1, t1

    def _noise(self, t0: int, t1: int, frame1: np.ndarray,
               parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> None:
        cfg, rng = self.config, self.rng
        dt_s = (t1 - t0) * 1e-6
        npix = self.width * self.height
        if cfg.shot_noise_hz > 0:
            # thinning: candidates at the darkest rate, kept with probability rate/max_rate
            k = int(rng.poisson(cfg.shot_noise_hz * _SHOT_DARK * npix * dt_s))
            if k:
                pix = rng.integers(0, npix, k)
                u = rng.random(k)
                t_ev = t0 + rng.random(k) * (t1 - t0)
                pol = np.where(rng.random(k) < 0.5, 1, -1).astype(np.int8)
                inten = np.clip(frame1.reshape(-1)[pix].astype(np.float64), 0.0, 1.0)
                keep = u * _SHOT_DARK < _SHOT_DARK - _SHOT_SLOPE * inten
                parts.append((pix[keep], np.rint(t_ev[keep]).astype(np.int64), pol[keep]))
        if len(self._hot_idx):
            cnt = rng.poisson(cfg.hot_pixel_hz * dt_s, len(self._hot_idx))
            total = int(cnt.sum())
            if total:
                sel = np.repeat(np.arange(len(self._hot_idx)), cnt)
                t_ev = t0 + rng.random(total) * (t1 - t0)
                parts.append((self._hot_idx[sel], np.rint(t_ev).astype(np.int64),
                              self._hot_pol[sel]))


def simulate_events(frames: np.ndarray, times_us: np.ndarray, config: SensorConfig,
                    rng: np.random.Generator) -> EventStream:
    """Events of a whole sequence: frames (S, H, W) linear [0, 1] at ``times_us`` (S,) int64.

    The first frame sets the initial state; events lie in ``[times_us[0], times_us[-1]]``,
    sorted by time. For long sequences use :class:`EventSensor` and feed chunks.
    """
    frames = np.asarray(frames)
    check_shape(frames, (None, None, None), "frames")
    sensor = EventSensor(config, frames.shape[2], frames.shape[1], rng)
    return sensor.feed(frames, times_us)
