"""Training data: simulated on the fly from still images, or read back from a pre-generated
trmd HDF5 file. Both yield the same dict of float32 tensors::

    blurry    (1, H, W)          blurry frame, [0, 1]
    voxels    (2N, H, W)         SCER voxels of its exposure (trmd_cli.voxel.scer_voxels)
    sharp     (2N+1, 1, H, W)    latent frames at k·T/(2N)
    contrast  ()                 true mean contrast threshold (NaN when the file has none)

:class:`SimulatedDataset` draws everything per sample from ``(seed, index)`` — image, view,
zoom, camera path, foreground layers, exposure time, brightness, sensor thresholds and noise —
so item ``i`` is the same in every epoch, process and worker, and the network sees a different
sensor in every sample (robustness to real cameras). The view is taken from the full source
image with a margin around the crop, so crops never show black borders.
"""

from __future__ import annotations

import math
import os
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError, InputError
from ..events import EventStream, Exposure
from ..voxel import scer_levels, scer_voxels
from .sample import Sample, make_sample
from .sensor import SensorConfig
from .trajectory import MotionRanges, to_gray

__all__ = ["SensorRanges", "SimulatedDataset", "H5SampleDataset", "pregenerate",
           "DATASET_MOTION", "to_item"]

Range = tuple[float, float]

#: motion for training: camera translation log-uniform in 3.5–70 px per exposure (median
#: ≈ 16 px; 42 % of samples above 20 px — real DAVIS frames show 20–70 px of blur), plus
#: rotation, zoom and perspective; foreground layers in a third of the samples
DATASET_MOTION = MotionRanges(translation_px=70.0, rotation_deg=3.0, scale=0.05,
                              perspective=0.02, curvature=0.5, foreground_prob=0.3,
                              max_layers=2, layer_translation_px=60.0, layer_size=(0.2, 0.6),
                              margin=0.45, log_magnitude=True)


@dataclass(frozen=True)
class SensorRanges:
    """Ranges (low, high) from which each sample's sensor is drawn uniformly.

    Defaults cover DAVIS240/346 cameras at usual biases and then some: mean threshold
    0.1–0.5, ON/OFF asymmetry up to ±25 %, mismatch σ up to 0.06, refractory up to 0.3 ms,
    shot noise up to 1 Hz/pixel, leak up to 0.2 Hz, up to 2·10⁻⁴ hot pixels at 10–100 Hz.
    ``clean_prob`` of the samples get an ideal sensor (threshold still drawn).

    Attributes:
        contrast: mean of ON and OFF thresholds.
        on_off_ratio: c_on / c_off, drawn log-uniformly.
        contrast_sigma, refractory_us, shot_noise_hz, leak_hz, hot_pixel_fraction,
        hot_pixel_hz, eps: as in :class:`SensorConfig`.
        clean_prob: probability of a noise-free sensor.
    """

    contrast: Range = (0.1, 0.5)
    on_off_ratio: Range = (0.8, 1.25)
    contrast_sigma: Range = (0.0, 0.06)
    refractory_us: Range = (0.0, 300.0)
    shot_noise_hz: Range = (0.0, 1.0)
    leak_hz: Range = (0.0, 0.2)
    hot_pixel_fraction: Range = (0.0, 2e-4)
    hot_pixel_hz: Range = (10.0, 100.0)
    eps: Range = (0.005, 0.02)
    clean_prob: float = 0.1

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "clean_prob":
                if not 0 <= v <= 1:
                    raise InputError(f"sensor_ranges.clean_prob must be in [0, 1], got {v}")
                continue
            object.__setattr__(self, f.name, _range(f"sensor_ranges.{f.name}", v, low=0.0))
        if self.contrast[0] <= 0 or self.on_off_ratio[0] <= 0 or self.eps[0] <= 0:
            raise InputError("sensor_ranges.contrast, on_off_ratio and eps must be > 0")

    def draw(self, rng: np.random.Generator) -> SensorConfig:
        def u(r: Range) -> float:
            return float(rng.uniform(*r)) if r[1] > r[0] else r[0]

        c = u(self.contrast)
        ratio = math.exp(u((math.log(self.on_off_ratio[0]), math.log(self.on_off_ratio[1]))))
        c_on, c_off = 2 * c * ratio / (1 + ratio), 2 * c / (1 + ratio)
        eps = u(self.eps)
        noisy = {k: u(getattr(self, k)) for k in ("contrast_sigma", "refractory_us",
                                                  "shot_noise_hz", "leak_hz",
                                                  "hot_pixel_fraction", "hot_pixel_hz")}
        if rng.random() < self.clean_prob:
            return SensorConfig(contrast_on=c_on, contrast_off=c_off, contrast_sigma=0.0,
                                refractory_us=0.0, shot_noise_hz=0.0, leak_hz=0.0,
                                hot_pixel_fraction=0.0, eps=eps, random_phase=False)
        return SensorConfig(contrast_on=c_on, contrast_off=c_off, eps=eps, random_phase=True,
                            **noisy)


def _range(name: str, value, *, low: float, open_low: bool = False) -> tuple[float, float]:
    """``value`` as a range ``(lo, hi)`` of finite numbers with ``low ≤ lo ≤ hi`` (``low < lo``
    when ``open_low``); one clear line naming ``name`` otherwise."""
    bound = f"{low:g} < low" if open_low else f"{low:g} ≤ low"
    try:
        lo, hi = (float(x) for x in value)
    except (TypeError, ValueError):
        raise InputError(f"{name} = {value!r} is not a range [low, high]",
                         hint=f"e.g. {name} = [1.0, 2.0]") from None
    ok = math.isfinite(lo) and math.isfinite(hi) and lo <= hi and (lo > low if open_low
                                                                    else lo >= low)
    if not ok:
        raise InputError(f"{name} = {value!r} is not a range {bound} ≤ high",
                         hint=f"e.g. {name} = [1.0, 2.0]")
    return lo, hi


def _coerce(cls, value, name: str):
    """A dataclass instance from an instance, a dict (TOML recipes) or None (defaults)."""
    if value is None:
        return cls() if name != "motion" else DATASET_MOTION
    if isinstance(value, cls):
        return value
    if isinstance(value, dict):
        known = {f.name for f in fields(cls)}
        bad = sorted(set(value) - known)
        if bad:
            raise InputError(f"{name} has unknown key(s) {', '.join(bad)}",
                             hint="known: " + ", ".join(sorted(known)))
        base = asdict(cls()) if name != "motion" else asdict(DATASET_MOTION)
        base.update({k: tuple(v) if isinstance(v, list) else v for k, v in value.items()})
        return cls(**base)
    raise InputError(f"{name} must be a {cls.__name__} or a table of its fields")


def to_item(sample: Sample, n: int, levels: bool = False) -> dict[str, Any]:
    """The dataset dict (torch tensors) of one :class:`Sample`; with ``levels``, also the
    voxels' sub-bin timing (:func:`~trmd_cli.voxel.scer_levels`)."""
    import torch

    vox = scer_voxels(sample.events, sample.exposure, n)
    item = {
        "blurry": torch.from_numpy(np.ascontiguousarray(sample.blurry[None], np.float32)),
        "voxels": torch.from_numpy(np.ascontiguousarray(vox, np.float32)),
        "sharp": torch.from_numpy(np.ascontiguousarray(sample.sharp[:, None], np.float32)),
        "contrast": torch.tensor(float(sample.contrast), dtype=torch.float32),
    }
    if levels:
        item["levels"] = torch.from_numpy(scer_levels(sample.events, sample.exposure, n))
    return item


class _ImageCache:
    """Gray float32 images by index, loaded lazily, least recently used evicted."""

    def __init__(self, images: Sequence[Path | str | np.ndarray], capacity: int = 64):
        self.images, self.capacity = list(images), capacity
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()

    def __len__(self) -> int:
        return len(self.images)

    def get(self, i: int) -> np.ndarray:
        src = self.images[i]
        if isinstance(src, np.ndarray):
            return to_gray(src)
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        from ..read.frames import read_image

        img = to_gray(read_image(src))
        self._cache[i] = img
        if len(self._cache) > self.capacity:
            self._cache.popitem(last=False)
        return img


def _torch_dataset_base():
    try:
        from torch.utils.data import Dataset
    except ImportError:  # pragma: no cover - torch is a dependency
        return object
    return Dataset


class SimulatedDataset(_torch_dataset_base()):  # type: ignore[misc]
    """Blurry crops, their events (as SCER voxels) and sharp ground truth, simulated per item.

    Args:
        images: still images (paths or arrays, gray or RGB; treated as linear intensity).
        n: 2N+1 latent frames.
        crop: output size (crop × crop) in pixels.
        length: number of items (an epoch).
        seed: base seed; item ``i`` depends only on ``(seed, i)``.
        channels: must be 1 (the event sensor is monochrome).
        sensor_ranges: :class:`SensorRanges` or a dict of its fields.
        motion: :class:`MotionRanges` or a dict of its fields (default :data:`DATASET_MOTION`).
        exposure_ms: range of the exposure time (sets noise per exposure; motion is per
            exposure whatever its length).
        gain: range of a brightness factor applied to the image (real DAVIS frames are dark).
        read_noise: range of σ of Gaussian read noise on the blurry frame.
        zoom: range of source pixels per output pixel (capped by what fits the image).
        max_px_per_step: largest image motion between simulation sub-steps, px.
        levels: items also carry ``levels``, the voxels' sub-bin timing
            (:func:`~trmd_cli.voxel.scer_levels`), for networks with ``timing``.
    """

    def __init__(self, images: Sequence[Path | str | np.ndarray], *, n: int = 3,
                 crop: int = 128, length: int = 6000, seed: int = 0, channels: int = 1,
                 sensor_ranges: SensorRanges | dict | None = None,
                 motion: MotionRanges | dict | None = None,
                 exposure_ms: Range = (10.0, 100.0), gain: Range = (0.25, 1.0),
                 read_noise: Range = (0.0, 0.02), zoom: Range = (1.0, 2.0),
                 max_px_per_step: float = 1.0, levels: bool = False):
        if not len(images):
            raise InputError("no images to simulate from", hint="pass image files or a folder")
        if channels != 1:
            raise InputError(f"simulated data is gray (1 channel), the recipe asks for {channels}",
                             hint="set model.channels = 1")
        if n < 1 or crop < 8 or length < 1:
            raise InputError(f"bad dataset sizes: n={n}, crop={crop}, length={length}")
        self.images = _ImageCache(images)
        self.n, self.crop, self.length, self.seed = int(n), int(crop), int(length), int(seed)
        self.sensor_ranges = _coerce(SensorRanges, sensor_ranges, "sensor_ranges")
        self.motion = _coerce(MotionRanges, motion, "motion")
        self.exposure_ms = _range("exposure_ms", exposure_ms, low=0.0, open_low=True)
        self.gain = _range("gain", gain, low=0.0, open_low=True)
        self.read_noise = _range("read_noise", read_noise, low=0.0)
        self.zoom = _range("zoom", zoom, low=0.0, open_low=True)
        self.max_px_per_step = float(max_px_per_step)
        self.levels = bool(levels)

    def __len__(self) -> int:
        return self.length

    def sample(self, index: int) -> Sample:
        """The numpy :class:`Sample` behind item ``index`` (exposure ``[0, T]``)."""
        if not 0 <= index < self.length:
            raise IndexError(index)
        rng = np.random.default_rng([self.seed, int(index)])
        img = self.images.get(int(rng.integers(len(self.images))))
        gain = rng.uniform(*self.gain)
        sensor = self.sensor_ranges.draw(rng)
        # a multiple of 2N µs, so the 2N voxel bins have equal integer widths
        step = 2 * self.n
        exposure_us = int(round(rng.uniform(*self.exposure_ms) * 1000 / step)) * step
        read_noise = rng.uniform(*self.read_noise)
        return make_sample(img * np.float32(gain), n=self.n, size=(self.crop, self.crop),
                           exposure_us=exposure_us, rng=rng, sensor=sensor, motion=self.motion,
                           read_noise=read_noise, max_px_per_step=self.max_px_per_step,
                           zoom=self.zoom)

    def __getitem__(self, index: int) -> dict[str, Any]:
        return to_item(self.sample(int(index)), self.n, self.levels)


class H5SampleDataset(_torch_dataset_base()):  # type: ignore[misc]
    """Items of a trmd HDF5 file with frames (``trmd simulate`` or :func:`pregenerate`).

    Voxels are computed from the file's events in each frame's exposure window. Gray frames
    give ``(1, H, W)``; RGB frames ``(3, H, W)``.

    Args:
        path: the .h5 file.
        n: 2N+1 latent frames; default from ``frames/sharp`` (required when it is absent).
        levels: items also carry ``levels`` (:func:`~trmd_cli.voxel.scer_levels`).

    Raises:
        FormatError: not a trmd HDF5 file with ``frames/blurry``.
    """

    def __init__(self, path: str | Path, n: int | None = None, levels: bool = False):
        import h5py

        from ..read.hdf5_strings import read_attr

        self.path = Path(path)
        self.levels = bool(levels)
        try:
            with h5py.File(self.path, "r") as f:
                if read_attr(f, "format") != "trmd" or "frames" not in f \
                        or "blurry" not in f["frames"]:
                    raise FormatError("not a trmd HDF5 file with frames/blurry", path=path,
                                      hint="write one with `trmd simulate`")
                g = f["frames"]
                self._len = int(g["blurry"].shape[0])
                self.width, self.height = int(read_attr(f, "width")), int(read_attr(f, "height"))
                self.has_sharp = "sharp" in g
                self.starts = g["exposure_start"][:].astype(np.int64)
                self.ends = g["exposure_end"][:].astype(np.int64)
                self.contrast = (g["contrast"][:].astype(np.float32) if "contrast" in g
                                 else np.full(self._len, np.nan, np.float32))
                if self.has_sharp:
                    n_file = (int(g["sharp"].shape[1]) - 1) // 2
                    if n is not None and n != n_file:
                        raise InputError(f"the file holds 2N+1 = {2 * n_file + 1} sharp frames, "
                                         f"not {2 * n + 1}", path=path,
                                         hint=f"use N = {n_file}")
                    n = n_file
                if n is None:
                    raise InputError("the file has no sharp frames, so N must be given",
                                     path=path)
                self.lo, self.hi = _event_ranges(f["events"]["t"], self.starts, self.ends)
        except OSError as e:
            raise FormatError(f"not a readable HDF5 file ({e})", path=path) from None
        self.n = int(n)
        self._file = None
        self._pid = -1

    def __len__(self) -> int:
        return self._len

    def _h5(self):
        import h5py

        # one handle per process: h5py handles must not cross a fork
        if self._file is None or self._pid != os.getpid():
            self._file = h5py.File(self.path, "r")
            self._pid = os.getpid()
        return self._file

    def events(self, index: int) -> EventStream:
        ev = self._h5()["events"]
        a, b = int(self.lo[index]), int(self.hi[index])
        return EventStream(ev["x"][a:b], ev["y"][a:b], ev["t"][a:b], ev["p"][a:b],
                           self.width, self.height)

    def __getitem__(self, index: int) -> dict[str, Any]:
        import torch

        if not 0 <= index < self._len:
            raise IndexError(index)
        g = self._h5()["frames"]
        exposure = Exposure(int(self.starts[index]), int(self.ends[index]))
        events = self.events(index)
        vox = scer_voxels(events, exposure, self.n)
        blurry = np.asarray(g["blurry"][index], np.float32)
        item = {
            "blurry": torch.from_numpy(_chw(blurry)),
            "voxels": torch.from_numpy(vox),
            "contrast": torch.tensor(float(self.contrast[index]), dtype=torch.float32),
        }
        if self.levels:
            item["levels"] = torch.from_numpy(scer_levels(events, exposure, self.n))
        if self.has_sharp:
            sharp = np.asarray(g["sharp"][index], np.float32)
            item["sharp"] = torch.from_numpy(np.stack([_chw(s) for s in sharp]))
        return item

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_file"], state["_pid"] = None, -1
        return state


def _chw(img: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(img[None] if img.ndim == 2 else np.moveaxis(img, -1, 0))


def _event_ranges(t_ds, starts: np.ndarray, ends: np.ndarray,
                  chunk: int = 1 << 22) -> tuple[np.ndarray, np.ndarray]:
    """Index ranges ``[lo, hi)`` of events with ``start ≤ t ≤ end`` per window, reading the
    (sorted) time dataset once in chunks (bounded memory)."""
    lo = np.zeros(len(starts), np.int64)
    hi = np.zeros(len(ends), np.int64)
    total = int(t_ds.shape[0])
    for a in range(0, total, chunk):
        t = t_ds[a:a + chunk]
        lo += np.searchsorted(t, starts, side="left")
        hi += np.searchsorted(t, ends, side="right")
    return lo, hi


def pregenerate(*args, **kwargs):
    """See :func:`trmd_cli.simulate.pregen.pregenerate`."""
    from .pregen import pregenerate as _pregenerate

    return _pregenerate(*args, **kwargs)
