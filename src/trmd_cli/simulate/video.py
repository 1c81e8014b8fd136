"""Sharp sequences from a video file or a folder of frames: temporal upsampling with optical flow.

Ordinary videos move many pixels between frames; simulating events straight from them would
quantise every event to a frame time. Between consecutive frames ``I0`` (time τ0) and ``I1``
(τ1) we estimate forward and backward flow with OpenCV's DIS and synthesise frames at
``α = (t − τ0)/(τ1 − τ0)`` with the linear flow approximation of Super SloMo (Jiang et al.,
CVPR 2018)::

    F_t→0 = −(1 − α)·α·F_0→1 + α²·F_1→0        F_t→1 = (1 − α)²·F_0→1 − α·(1 − α)·F_1→0
    I_t = (1 − α)·I0(x + F_t→0) + α·I1(x + F_t→1)

(no occlusion reasoning: occluded regions cross-fade). Each interval gets enough sub-steps that
the flow (its 99.5th percentile magnitude) moves at most ``max_px_per_step`` pixels per step.
Frames are converted to gray, resized to cover the output size and centre-cropped, and treated
as linear intensity.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..events import EventStream, Exposure
from ..read.frames import IMAGE_EXTENSIONS, read_image
from .blur import ExposureResult, latent_times, run_exposures
from .sensor import EventSensor, SensorConfig
from .trajectory import to_gray

__all__ = ["VIDEO_EXTENSIONS", "list_frames", "read_timestamps", "FrameSource", "FolderFrames",
           "VideoFrames", "fit_frame", "FlowInterpolator", "video_blocks", "video_exposures",
           "iter_video"]

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv")
#: percentile of the flow magnitude that sets the number of sub-steps (robust to outliers)
_FLOW_PERCENTILE = 99.5


def _natural_key(path: Path) -> list:
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", path.name)]


def list_frames(folder: str | Path) -> list[Path]:
    """Image files of ``folder`` in natural name order (frame2 before frame10).

    Raises:
        InputError: no image files in the folder.
    """
    folder = Path(folder)
    files = sorted((p for p in folder.iterdir()
                    if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
                    and not p.name.startswith(".")), key=_natural_key)
    if len(files) < 2:
        raise InputError(f"the folder holds {len(files)} image file(s), at least 2 are needed",
                         path=folder, hint="use " + ", ".join(IMAGE_EXTENSIONS))
    return files


#: the longest median spacing of a frame folder's or video's timestamps, seconds
MAX_FRAME_SPACING_S = 10.0


def read_timestamps(path: str | Path, count: int) -> np.ndarray:
    """One time in seconds per line (blank lines and ``#`` comments skipped) → int64 µs.

    Raises:
        InputError: wrong count, not numbers, not strictly increasing, negative, or frames
            more than :data:`MAX_FRAME_SPACING_S` apart (a unit mistake).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("timestamps file not found", path=path, hint="check the path")
    values = []
    for no, line in enumerate(path.read_text().splitlines(), 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        try:
            values.append(float(text.split()[0].rstrip(",")))
        except ValueError:
            raise InputError(f"line {no} is not a time in seconds: {line.strip()!r}",
                             path=path) from None
    t = np.array(values, np.float64)
    if len(t) != count:
        raise InputError(f"{len(t)} timestamps for {count} frames", path=path,
                         hint="give one time in seconds per frame, in frame order")
    if not np.isfinite(t).all() or (t < 0).any():
        raise InputError("timestamps must be finite and ≥ 0", path=path)
    us = np.rint(t * 1e6).astype(np.int64)
    if (np.diff(us) <= 0).any():
        bad = int(np.flatnonzero(np.diff(us) <= 0)[0]) + 1
        raise InputError(f"timestamp {bad + 1} does not increase", path=path,
                         hint="times must increase strictly, in seconds")
    if len(t) > 1 and float(np.median(np.diff(t))) > MAX_FRAME_SPACING_S:
        # a video's frames are milliseconds apart: times in ms or µs read as seconds would
        # have the simulator sweep hours between frames
        raise InputError(f"the frames are {float(np.median(np.diff(t))):g} s apart (median): "
                         "are the times in ms or µs?", path=path,
                         hint="write one time in seconds per frame, e.g. 0.033 for 33 ms")
    return us


def fit_frame(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Gray, resized to cover ``size`` (W, H) keeping the aspect ratio, centre-cropped."""
    import cv2

    g = to_gray(image)
    w, h = size
    k = max(w / g.shape[1], h / g.shape[0])
    nw, nh = max(w, round(g.shape[1] * k)), max(h, round(g.shape[0] * k))
    if (nw, nh) != (g.shape[1], g.shape[0]):
        interp = cv2.INTER_AREA if k < 1 else cv2.INTER_LINEAR
        g = cv2.resize(g, (nw, nh), interpolation=interp)
    x0, y0 = (nw - w) // 2, (nh - h) // 2
    return np.ascontiguousarray(g[y0:y0 + h, x0:x0 + w])


class FrameSource:
    """Frames in time order, read on demand: ``times_us`` (F,) and ``frame(i)`` (H, W)."""

    times_us: np.ndarray
    size: tuple[int, int]

    def __len__(self) -> int:
        return len(self.times_us)

    def frame(self, i: int) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError


class FolderFrames(FrameSource):
    """Image files at given times (µs)."""

    def __init__(self, paths: list[Path], times_us: np.ndarray, size: tuple[int, int]):
        self.paths, self.times_us, self.size = paths, np.asarray(times_us, np.int64), size
        if len(paths) != len(self.times_us):
            raise InputError(f"{len(paths)} frames but {len(self.times_us)} times")
        self._cache: dict[int, np.ndarray] = {}

    def frame(self, i: int) -> np.ndarray:
        if i not in self._cache:
            self._cache = {k: v for k, v in self._cache.items() if k >= i - 1}
            self._cache[i] = fit_frame(read_image(self.paths[i]), self.size)
        return self._cache[i]


class VideoFrames(FrameSource):
    """A video file read sequentially with OpenCV (frames must be requested in order)."""

    def __init__(self, path: str | Path, size: tuple[int, int], fps: float | None = None,
                 times_us: np.ndarray | None = None):
        import cv2

        self.path, self.size = Path(path), size
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise FormatError("not a readable video", path=path,
                              hint="use an mp4/avi file, or a folder of frames")
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        cap.release()
        if count < 2:
            count = sum(1 for _ in self._iter_raw())
        if count < 2:
            raise FormatError(f"the video has {count} frame(s), at least 2 are needed", path=path)
        if times_us is None:
            fps = fps or self.container_fps()
            if not fps or fps <= 0:
                raise InputError("the video does not say its frame rate", path=path,
                                 hint="pass `fps` or `times_us`")
            times_us = np.rint(np.arange(count) * (1e6 / fps)).astype(np.int64)
        self.times_us = np.asarray(times_us, np.int64)
        if len(self.times_us) != count:
            raise InputError(f"{len(self.times_us)} times for {count} video frames", path=path)
        self._reader: Iterator[np.ndarray] | None = None
        self._next = 0
        self._cache: dict[int, np.ndarray] = {}

    def container_fps(self) -> float:
        import cv2

        cap = cv2.VideoCapture(str(self.path))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        cap.release()
        return fps

    def _iter_raw(self) -> Iterator[np.ndarray]:
        import cv2

        cap = cv2.VideoCapture(str(self.path))
        try:
            while True:
                ok, img = cap.read()
                if not ok:
                    return
                yield img
        finally:
            cap.release()

    def frame(self, i: int) -> np.ndarray:
        if i in self._cache:
            return self._cache[i]
        if self._reader is None or i < self._next:
            self._reader, self._next = self._iter_raw(), 0
        img = None
        while self._next <= i:
            img = next(self._reader, None)
            if img is None:
                raise FormatError(f"the video ended before frame {i}", path=self.path)
            self._next += 1
        rgb = img[..., ::-1] if img.ndim == 3 else img
        self._cache = {k: v for k, v in self._cache.items() if k >= i - 1}
        self._cache[i] = fit_frame(rgb, self.size)
        return self._cache[i]


class FlowInterpolator:
    """Frames between two sharp frames by bidirectional DIS flow (see module docstring)."""

    def __init__(self, i0: np.ndarray, i1: np.ndarray):
        import cv2

        self.i0, self.i1 = i0, i1
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        u0 = np.clip(i0 * 255 + 0.5, 0, 255).astype(np.uint8)
        u1 = np.clip(i1 * 255 + 0.5, 0, 255).astype(np.uint8)
        self.f01 = dis.calc(u0, u1, None)
        self.f10 = dis.calc(u1, u0, None)
        h, w = i0.shape
        self.gx, self.gy = np.meshgrid(np.arange(w, dtype=np.float32),
                                       np.arange(h, dtype=np.float32))

    def motion_px(self) -> float:
        """Robust largest flow magnitude between the two frames, px."""
        m = max(np.percentile(np.hypot(f[..., 0], f[..., 1]), _FLOW_PERCENTILE)
                for f in (self.f01, self.f10))
        return float(m)

    def __call__(self, alpha: float) -> np.ndarray:
        import cv2

        if alpha <= 0:
            return self.i0.copy()
        if alpha >= 1:
            return self.i1.copy()
        a = float(alpha)
        ft0 = -(1 - a) * a * self.f01 + a * a * self.f10
        ft1 = (1 - a) * (1 - a) * self.f01 - a * (1 - a) * self.f10
        w0 = cv2.remap(self.i0, self.gx + ft0[..., 0], self.gy + ft0[..., 1], cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE)
        w1 = cv2.remap(self.i1, self.gx + ft1[..., 0], self.gy + ft1[..., 1], cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE)
        return (1 - a) * w0 + a * w1


def video_blocks(source: FrameSource, exposures: list[Exposure], n: int, *,
                 max_px_per_step: float = 1.0,
                 on_interval: Callable[[int, int], None] | None = None,
                 ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Sub-step blocks (times (b,) int64 µs, frames (b, H, W)) over the source's whole span.

    One block per source interval ``(τ_i, τ_{i+1}]`` (the first block also holds τ_0): uniform
    steps sized by the flow, plus every exposure start/end/latent instant that falls inside.
    ``on_interval(i, count)`` reports progress.
    """
    times = source.times_us
    required = np.unique(np.concatenate(
        [latent_times(e, n) for e in exposures] or [np.zeros(0, np.int64)]))
    yield times[:1], source.frame(0)[None]
    for i in range(len(times) - 1):
        t0, t1 = int(times[i]), int(times[i + 1])
        interp = FlowInterpolator(source.frame(i), source.frame(i + 1))
        steps = max(1, int(math.ceil(interp.motion_px() / max_px_per_step)))
        steps = min(steps, t1 - t0)
        grid = np.rint(np.linspace(t0, t1, steps + 1)[1:]).astype(np.int64)
        extra = required[(required > t0) & (required < t1)]
        grid = np.unique(np.concatenate([grid, extra]))
        frames = np.stack([interp((t - t0) / (t1 - t0)) for t in grid]).astype(np.float32)
        if on_interval is not None:
            on_interval(i + 1, len(times) - 1)
        yield grid, frames


def video_exposures(times_us: np.ndarray, exposure_us: int | None, interval_us: int | None,
                    frames: int | None) -> list[Exposure]:
    """Exposure windows over a source's span ``[τ_0, τ_last]``.

    Defaults: exposure = 3 source frame intervals (median), interval = 1.2 × exposure, as many
    frames as fit (``frames`` caps the count).

    Raises:
        InputError: not even one exposure fits in the span.
    """
    times_us = np.asarray(times_us, np.int64)
    dt = float(np.median(np.diff(times_us)))
    exp_us = int(round(3 * dt)) if exposure_us is None else int(exposure_us)
    if exp_us < 2:
        raise InputError(f"exposure of {exp_us} µs is too short")
    step = int(round(1.2 * exp_us)) if interval_us is None else int(interval_us)
    if step < exp_us:
        raise InputError(f"frame interval {step} µs is shorter than the exposure {exp_us} µs",
                         hint="raise `interval_us`")
    start, end = int(times_us[0]), int(times_us[-1])
    fit = (end - start - exp_us) // step + 1 if end - start >= exp_us else 0
    count = fit if frames is None else min(fit, int(frames))
    if count < 1:
        raise InputError(f"a {exp_us / 1000:g} ms exposure does not fit in the "
                         f"{(end - start) / 1000:g} ms the frames span",
                         hint="use a shorter `exposure_us`, more frames, or a lower `fps`")
    return [Exposure(start + k * step, start + k * step + exp_us) for k in range(count)]


def iter_video(source: FrameSource, exposures: list[Exposure], *, n: int = 3,
               sensor: SensorConfig | None = None, rng: np.random.Generator,
               read_noise: float = 0.0, max_px_per_step: float = 1.0,
               on_interval: Callable[[int, int], None] | None = None,
               ) -> tuple[EventSensor, Iterator[EventStream | ExposureResult]]:
    """Events over the source's whole span and the given exposures, streamed.

    Returns ``(EventSensor, iterator of EventStream | ExposureResult)`` like
    :func:`trmd_cli.simulate.iter_sequence`.
    """
    cfg = SensorConfig() if sensor is None else sensor
    sensor_rng, noise_rng = (np.random.default_rng(s) for s in rng.integers(0, 2**63 - 1, 2))
    w, h = source.size
    ev_sensor = EventSensor(cfg, w, h, sensor_rng)
    blocks = video_blocks(source, exposures, n, max_px_per_step=max_px_per_step,
                          on_interval=on_interval)
    return ev_sensor, run_exposures(blocks, exposures, n, ev_sensor, read_noise=read_noise,
                                    noise_rng=noise_rng)
