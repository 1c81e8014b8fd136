"""HDF5 event files, read lazily: windows are found by binary search on the time dataset and
only their slice is read, so memory is bounded by one window, not the file.

Layouts (docs/formats.md):
- trmd (root attr ``format="trmd"``): ``events/x,y`` uint16, ``events/t`` int64 µs, ``events/p``
  int8 ±1, root attrs ``width``, ``height``; optional ``frames/blurry`` (K, H, W[, 3]) float [0,1],
  ``frames/exposure_start|exposure_end`` (K,) int64 µs, ``frames/sharp`` (K, 2N+1, H, W[, 3]),
  ``frames/contrast`` (K,).
- event_utils / E2VID: ``events/xs, ys, ts, ps`` (ts float seconds), root attr
  ``sensor_resolution`` (H, W).
- DSEC: ``events/x, y, t, p`` with t in µs relative to the root dataset ``t_offset``; Blosc
  compression needs the optional ``hdf5plugin`` (``pip install 'trmd[dsec]'``).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..events import EventStream, Exposure, make_stream
from .base import Frame, ReadOptions, Recording
from .units import to_microseconds

__all__ = ["read_hdf5", "HDF5Recording"]

_LAYOUTS = {
    "trmd/dsec": ("x", "y", "t", "p"),
    "event_utils": ("xs", "ys", "ts", "ps"),
}
#: the coarse index keeps every STRIDE-th time in memory (8 bytes / 4096 events)
STRIDE = 4096


class HDF5Recording(Recording):
    """An HDF5 event file opened for lazy window reads."""

    def __init__(self, path: Path, options: ReadOptions):
        try:
            self._open(path, options)
        except FormatError:
            self.close()
            raise
        except InputError:
            self.close()
            raise
        except (KeyError, OSError, ValueError, RuntimeError) as e:
            # h5py reports damage in many shapes; all mean the same to a user
            self.close()
            raise FormatError(f"cannot be read, truncated or corrupt ({e})", path=path) from None

    def _open(self, path: Path, options: ReadOptions) -> None:
        import h5py

        try:
            import hdf5plugin  # noqa: F401  (registers Blosc etc. when installed)
        except ImportError:
            pass
        self.path, self.format, self.warnings = path, "hdf5", []
        try:
            self._f = h5py.File(path, "r")
        except OSError as e:
            raise FormatError(f"cannot be opened as HDF5, truncated or corrupt ({e})",
                              path=path) from None
        f = self._f
        if "events" not in f:
            raise FormatError(f"no 'events' group (top-level keys: {', '.join(f.keys()) or 'none'})",
                              path=path, hint="expected events/x, events/y, events/t, events/p")
        ev = f["events"]
        keys = next((ks for ks in _LAYOUTS.values() if all(k in ev for k in ks)), None)
        if keys is None:
            raise FormatError(f"events group lacks x/y/t/p datasets (has: {', '.join(ev.keys())})",
                              path=path, hint="expected events/x, y, t, p or events/xs, ys, ts, ps")
        self._x, self._y, self._t, self._p = (ev[k] for k in keys)
        n = self._t.shape[0]
        if any(d.shape[0] != n for d in (self._x, self._y, self._p)):
            raise FormatError("event datasets differ in length", path=path)
        self.layout = ("trmd" if f.attrs.get("format") in ("trmd", b"trmd")
                       else "event_utils" if keys[0] == "xs" else "dsec")
        self._unit = options.time_unit
        if self._unit is None:
            self._unit = "s" if self._t.dtype.kind == "f" else "us"
        self._offset_us = 0
        if "t_offset" in f:
            self._offset_us = int(np.asarray(f["t_offset"][()]).ravel()[0])
        self._one_based = options.one_based
        width = height = None
        if options.sensor is not None:
            width, height = options.sensor
        elif "width" in f.attrs and "height" in f.attrs:
            width, height = int(f.attrs["width"]), int(f.attrs["height"])
        elif "sensor_resolution" in f.attrs:
            height, width = (int(v) for v in f.attrs["sensor_resolution"][:2])
        elif "frames/blurry" in f:
            height, width = f["frames/blurry"].shape[1:3]
        if width is None:
            # a size must be fixed now for lazy windows to agree: one pass over x and y
            try:
                width = int(self._x[...].max()) + 1 if n else 1
                height = int(self._y[...].max()) + 1 if n else 1
            except OSError as e:
                    raise self._read_error(e) from None
            self.warnings.append("the file stores no sensor size: using max+1 of the "
                                 "coordinates (pass --sensor WxH to set it)")
        self.width, self.height = int(width), int(height)
        try:
            coarse = self._times(self._t[::STRIDE]) if n else np.zeros(0, np.int64)
        except OSError as e:
            raise self._read_error(e) from None
        if len(coarse) > 1 and (np.diff(coarse) < 0).any():
            raise InputError("event times are not sorted", path=path,
                             hint="sort the events by time (trmd convert sorts text/npz input)")
        self._coarse = coarse
        self._n = n

    def _read_error(self, e: Exception) -> FormatError:
        msg = str(e)
        if "filter" in msg.lower() or "plugin" in msg.lower():
            return FormatError("uses an HDF5 compression filter that is not installed", path=self.path,
                               hint="pip install 'trmd[dsec]' (hdf5plugin)")
        return FormatError(f"cannot be read, truncated or corrupt ({msg})", path=self.path)

    def _times(self, raw: np.ndarray) -> np.ndarray:
        return to_microseconds(raw, self._unit) + self._offset_us

    def _search(self, t_us: float, side: str) -> int:
        """Index of ``t_us`` in the full time dataset, reading one STRIDE block."""
        if t_us == -np.inf:
            return 0
        if t_us == np.inf:
            return self._n
        b = int(np.searchsorted(self._coarse, t_us, side=side))
        lo = max(0, (b - 1) * STRIDE)
        hi = min(self._n, b * STRIDE + 1)
        block = self._times(self._t[lo:hi])
        return lo + int(np.searchsorted(block, t_us, side=side))

    def events(self, start_us=None, end_us=None) -> EventStream:
        i0 = self._search(-np.inf if start_us is None else start_us, "left")
        i1 = self._search(np.inf if end_us is None else end_us, "left")
        return self.events_by_index(i0, i1)

    def events_by_index(self, i0: int, i1: int) -> EventStream:
        try:
            x, y, t, p = (d[i0:i1] for d in (self._x, self._y, self._t, self._p))
        except (OSError, KeyError, ValueError) as e:
            raise self._read_error(e) from None
        if self._one_based:
            x, y = x.astype(np.int64) - 1, y.astype(np.int64) - 1
        try:
            return make_stream(x, y, self._times(t), p, self.width, self.height,
                               source=str(self.path))
        except InputError as e:
            raise InputError(e.detail, path=self.path, hint=e.hint) from None

    def num_events(self) -> int:
        return self._n

    def iter_chunks(self, max_events: int = 1 << 22) -> Iterator[EventStream]:
        for i0 in range(0, self._n, max_events):
            yield self.events_by_index(i0, min(self._n, i0 + max_events))

    def time_range_us(self) -> tuple[int, int]:
        if self._n == 0:
            return (0, 0)
        return int(self._times(self._t[:1])[0]), int(self._times(self._t[-1:])[0])

    # ---- frames (trmd layout)
    @property
    def num_frames(self) -> int:
        return self._f["frames/blurry"].shape[0] if "frames/blurry" in self._f else 0

    def frame_exposures(self) -> list[Exposure]:
        if "frames/exposure_start" not in self._f:
            return []
        s = self._f["frames/exposure_start"][...]
        e = self._f["frames/exposure_end"][...]
        return [Exposure(int(a), int(b)) for a, b in zip(s, e)]

    def frames(self) -> Iterator[Frame]:
        exposures = self.frame_exposures()
        for k in range(self.num_frames):
            img = np.asarray(self._f["frames/blurry"][k], np.float32)
            if img.dtype.kind in "ui" or img.max(initial=0) > 1.0 + 1e-6:
                img = img / (255.0 if img.max() <= 255 else 65535.0)
            yield Frame(img, exposures[k] if k < len(exposures) else None, k,
                        f"{self.path.name}#frame{k}")

    def frame(self, k: int) -> Frame:
        return next(f for i, f in enumerate(self.frames()) if i == k)

    @property
    def has_ground_truth(self) -> bool:
        return "frames/sharp" in self._f

    def ground_truth(self, k: int) -> np.ndarray:
        """(2N+1, H, W[, 3]) float32 latent frames of exposure k."""
        if not self.has_ground_truth:
            raise FormatError("holds no ground truth (frames/sharp)", path=self.path)
        return np.asarray(self._f["frames/sharp"][k], np.float32)

    def contrast(self, k: int) -> float | None:
        if "frames/contrast" not in self._f:
            return None
        return float(self._f["frames/contrast"][k])

    def close(self) -> None:
        f = getattr(self, "_f", None)
        if f is not None:
            f.close()
            self._f = None


def read_hdf5(path: Path, options: ReadOptions) -> HDF5Recording:
    return HDF5Recording(path, options)
