"""HDF5 event files, read lazily: windows are found by binary search on the time dataset and
only their slice is read, so memory is bounded by one window, not the file.

Layouts (docs/formats.md):
- trmd (root attr ``format="trmd"``): ``events/x,y`` uint16, ``events/t`` int64 µs, ``events/p``
  int8 ±1, root attrs ``width``, ``height``; optional ``frames/blurry`` (K, H, W[, 3]) float [0,1],
  ``frames/exposure_start|exposure_end`` (K,) int64 µs, ``frames/sharp`` (K, 2N+1, H, W[, 3]),
  ``frames/contrast`` (K,), ``frames/motion`` (K, J, 3, 3) the simulator's true camera path;
  ``windows/start_us|end_us`` (K,) int64 µs: windows without frames.
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
from ..units import times_unit, to_microseconds
from .base import Frame, ReadOptions, Recording
from .hdf5_strings import read_attr

__all__ = ["read_hdf5", "HDF5Recording"]

_LAYOUTS = {
    "trmd/dsec": ("x", "y", "t", "p"),
    "event_utils": ("xs", "ys", "ts", "ps"),
}
#: the largest value of a float ``frames/blurry`` read as [0, 1] intensity: sensor noise on a
#: bright pixel overshoots 1 (a σ = 0.01 frame whose highlights sit at 1.0 reaches ≈ 1.05), and
#: dividing such a frame by 255 would darken it 255× without a word. A float frame beyond this
#: holds 8-bit (≤ 255) or 16-bit counts and is scaled as integer frames are.
FLOAT_FRAME_MAX = 2.0

#: the coarse index keeps every STRIDE-th time in memory (8 bytes / 4096 events)
STRIDE = 4096


#: hint for files that cannot be decoded
_DAMAGED = "the file may be incomplete or damaged: copy it again or re-export it"


#: what h5py raises when a damaged file is read past its opening
_H5_ERRORS = (OSError, KeyError, ValueError, TypeError, RuntimeError)


def _names(group) -> str:
    """Member names for a message (damaged files can hold names that are not text)."""
    return ", ".join(str(k) for k in group.keys())


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
        except _H5_ERRORS as e:
            # h5py reports damage in many shapes; all mean the same to a user
            self.close()
            raise FormatError(f"cannot be read, truncated or corrupt ({e})", path=path,
                              hint=_DAMAGED) from None

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
                              path=path, hint=_DAMAGED) from None
        f = self._f
        if "events" not in f:
            raise FormatError(f"no 'events' group (top-level keys: {_names(f) or 'none'})",
                              path=path, hint="expected events/x, events/y, events/t, events/p")
        ev = f["events"]
        keys = next((ks for ks in _LAYOUTS.values() if all(k in ev for k in ks)), None)
        if keys is None:
            raise FormatError(f"events group lacks x/y/t/p datasets (has: {_names(ev)})",
                              path=path, hint="expected events/x, y, t, p or events/xs, ys, ts, ps")
        for k in keys:
            d = ev[k]
            if not isinstance(d, h5py.Dataset) or d.ndim != 1 or d.dtype.kind not in "iufb":
                what = ("a group" if not isinstance(d, h5py.Dataset) else
                        f"{d.dtype} of shape {d.shape}")
                raise FormatError(f"events/{k} is {what}, expected a 1-D numeric dataset",
                                  path=path, hint="store one number per event in each dataset")
        self._x, self._y, self._t, self._p = (ev[k] for k in keys)
        n = self._t.shape[0]
        if any(d.shape[0] != n for d in (self._x, self._y, self._p)):
            raise FormatError("event datasets differ in length "
                              f"({', '.join(f'{k}: {ev[k].shape[0]}' for k in keys)})",
                              path=path, hint="x, y, t and p need one entry per event")
        self.layout = ("trmd" if read_attr(f, "format") in ("trmd", b"trmd")
                       else "event_utils" if keys[0] == "xs" else "dsec")
        self._unit = self.times_unit = times_unit(self._t.dtype, options.time_unit)
        self._offset_us = 0
        if "t_offset" in f:
            off = np.asarray(f["t_offset"][()]).ravel()
            if off.size != 1 or off.dtype.kind not in "iu":
                raise FormatError(f"t_offset is {off[:4].tolist()}, expected one integer (µs)",
                                  path=path, hint="repair or remove the t_offset dataset")
            self._offset_us = int(off[0])
        self._one_based = options.one_based
        width = height = None
        try:
            if options.sensor is not None:
                width, height = options.sensor
            elif "width" in f.attrs and "height" in f.attrs:
                width, height = int(read_attr(f, "width")), int(read_attr(f, "height"))
            elif "sensor_resolution" in f.attrs:
                height, width = (int(v) for v in read_attr(f, "sensor_resolution")[:2])
            elif "frames/blurry" in f:
                height, width = f["frames/blurry"].shape[1:3]
            elif options.frame_size is not None:
                width, height = options.frame_size
        except (TypeError, ValueError, IndexError):
            raise FormatError("the stored sensor size is not two whole numbers", path=path,
                              hint="pass `sensor=(W, H)`") from None
        if width is not None and not (0 < width <= 65535 and 0 < height <= 65535):
            raise FormatError(f"the stored sensor size {width}x{height} is impossible", path=path,
                              hint="pass `sensor=(W, H)`")
        if width is None:
            # a size must be fixed now for lazy windows to agree: one pass over x and y
            try:
                width = int(self._x[...].max()) + 1 if n else 1
                height = int(self._y[...].max()) + 1 if n else 1
            except _H5_ERRORS as e:
                    raise self._read_error(e) from None
            self.warnings.append("the file stores no sensor size: using max+1 of the "
                                 "coordinates (pass `sensor=(W, H)` to set it)")
        self.width, self.height = int(width), int(height)
        try:
            coarse = self._times(self._t[::STRIDE]) if n else np.zeros(0, np.int64)
        except _H5_ERRORS as e:
            raise self._read_error(e) from None
        if len(coarse) and coarse.min() < 0:
            raise InputError(f"event times are negative ({int(coarse.min())} µs)", path=path,
                             hint="times must count from the start of the recording; check "
                                  "`time_unit` and t_offset")
        if len(coarse) > 1 and (np.diff(coarse) < 0).any():
            raise InputError("event times are not sorted", path=path,
                             hint="sort the events by time (trmd convert sorts text/npz input)")
        self._coarse = coarse
        self._n = n

    def _read_error(self, e: Exception) -> FormatError:
        msg = str(e)
        if "filter" in msg.lower() or "plugin" in msg.lower():
            return FormatError("uses an HDF5 compression filter that is not installed",
                               path=self.path,
                               hint="pip install 'trmd[dsec]' (hdf5plugin)")
        return FormatError(f"cannot be read, truncated or corrupt ({msg})", path=self.path,
                           hint=_DAMAGED)

    def _times(self, raw: np.ndarray) -> np.ndarray:
        try:
            return to_microseconds(raw, self._unit) + self._offset_us
        except InputError as e:
            raise InputError(e.detail, path=self.path, hint=e.hint) from None

    def _search(self, t_us: float, side: str) -> int:
        """Index of ``t_us`` in the full time dataset, reading one STRIDE block."""
        if t_us == -np.inf:
            return 0
        if t_us == np.inf:
            return self._n
        b = int(np.searchsorted(self._coarse, t_us, side=side))
        lo = max(0, (b - 1) * STRIDE)
        hi = min(self._n, b * STRIDE + 1)
        try:
            block = self._times(self._t[lo:hi])
        except _H5_ERRORS as e:
            raise self._read_error(e) from None
        return lo + int(np.searchsorted(block, t_us, side=side))

    def events(self, start_us=None, end_us=None) -> EventStream:
        i0 = self._search(-np.inf if start_us is None else start_us, "left")
        i1 = self._search(np.inf if end_us is None else end_us, "left")
        return self.events_by_index(i0, i1)

    def events_by_index(self, i0: int, i1: int) -> EventStream:
        try:
            x, y, t, p = (d[i0:i1] for d in (self._x, self._y, self._t, self._p))
        except _H5_ERRORS as e:
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

    def iter_events(self, start_us=None, end_us=None,
                    max_events: int = 1 << 22) -> Iterator[EventStream]:
        i0 = self._search(-np.inf if start_us is None else start_us, "left")
        i1 = self._search(np.inf if end_us is None else end_us, "left")
        for a in range(i0, i1, max(int(max_events), 1)):
            yield self.events_by_index(a, min(i1, a + max(int(max_events), 1)))

    def iter_chunks(self, max_events: int = 1 << 22) -> Iterator[EventStream]:
        for i0 in range(0, self._n, max_events):
            yield self.events_by_index(i0, min(self._n, i0 + max_events))

    def time_range_us(self) -> tuple[int, int]:
        if self._n == 0:
            return (0, 0)
        try:
            return int(self._times(self._t[:1])[0]), int(self._times(self._t[-1:])[0])
        except _H5_ERRORS as e:
            raise self._read_error(e) from None

    # ---- frames (trmd layout)
    @property
    def num_frames(self) -> int:
        try:
            if not self._has("frames/blurry"):
                return 0
            shape = self._f["frames/blurry"].shape
        except _H5_ERRORS as e:
            raise self._read_error(e) from None
        if shape is None or len(shape) not in (3, 4):
            raise FormatError(f"frames/blurry has shape {shape}, expected (K, H, W[, 3])",
                              path=self.path, hint="store the frames as one (K, H, W) dataset")
        return shape[0]

    def _has(self, name: str) -> bool:
        try:
            return name in self._f
        except _H5_ERRORS as e:
            raise self._read_error(e) from None

    def frame_exposures(self) -> list[Exposure]:
        if not self._has("frames/exposure_start"):
            return []
        if not self._has("frames/exposure_end"):
            raise FormatError("frames/exposure_start is stored without frames/exposure_end",
                              path=self.path, hint="store both, or give `exposure=(T0, T1)`")
        try:
            s = np.ravel(self._f["frames/exposure_start"][...])
            e = np.ravel(self._f["frames/exposure_end"][...])
        except _H5_ERRORS as err:
            raise self._read_error(err) from None
        ok = len(s) == len(e) and s.dtype.kind in "iu" and e.dtype.kind in "iu"
        bad = np.flatnonzero(e <= s) if ok else []
        if not ok or len(bad):
            what = (f"{len(s)} starts and {len(e)} ends" if len(s) != len(e) else
                    f"types {s.dtype}/{e.dtype}, expected integer µs" if not ok else
                    f"window {int(bad[0])} [{s[bad[0]]}, {e[bad[0]]}] µs is empty or reversed")
            raise FormatError(f"frames/exposure_start/end: {what}", path=self.path,
                              hint="repair the stored windows, or give `exposure=(T0, T1)`")
        self._one_per_frame("frames/exposure_start", len(s), "exposure windows")
        return [Exposure(int(a), int(b)) for a, b in zip(s, e, strict=True)]

    def _one_per_frame(self, name: str, count: int, what: str) -> None:
        """Refuse ``count`` entries of ``name`` for another number of stored frames: the
        layout keeps one per frame, and a frame without its own would vanish or take
        another's."""
        frames = self.num_frames
        if frames and count != frames:
            raise FormatError(f"{name} holds {count} {what} for {frames} frames in "
                              "frames/blurry", path=self.path,
                              hint="repair the file: the trmd layout stores one per frame")

    def stored_windows(self) -> list[Exposure]:
        if not self._has("windows/start_us"):
            return []
        try:
            s = np.ravel(self._f["windows/start_us"][...])
            e = np.ravel(self._f["windows/end_us"][...]) if self._has("windows/end_us") else None
        except _H5_ERRORS as err:
            raise self._read_error(err) from None
        if e is None or len(s) != len(e) or s.dtype.kind not in "iu" or e.dtype.kind not in "iu":
            raise FormatError("windows/start_us and windows/end_us must be integer µs of one "
                              "length", path=self.path,
                              hint="repair the stored windows, or give `exposure=(T0, T1)`")
        bad = np.flatnonzero(e <= s)
        if len(bad):
            k = int(bad[0])
            raise FormatError(f"windows: window {k} [{s[k]}, {e[k]}] µs is empty or reversed",
                              path=self.path,
                              hint="repair the stored windows, or give `exposure=(T0, T1)`")
        return [Exposure(int(a), int(b)) for a, b in zip(s, e, strict=True)]

    def frames(self) -> Iterator[Frame]:
        exposures = self.frame_exposures()
        for k in range(self.num_frames):
            try:
                img = np.asarray(self._f["frames/blurry"][k], np.float32)
            except _H5_ERRORS as e:
                raise self._read_error(e) from None
            bad = np.count_nonzero(~np.isfinite(img))
            if bad:
                raise InputError(f"frame {k} holds {bad} NaN or infinite pixel value(s)",
                                 path=self.path, hint="repair the stored frames: pixels are "
                                 "intensities in [0, 1]")
            if img.dtype.kind in "ui" or img.max(initial=0) > FLOAT_FRAME_MAX:
                img = img / (255.0 if img.max() <= 255 else 65535.0)
            if img.shape[:2] != (self.height, self.width):
                raise InputError(f"frame {k} is {img.shape[1]}x{img.shape[0]} but the events' "
                                 f"sensor is {self.width}x{self.height}", path=self.path,
                                 hint="store frames of the sensor size, or pass `sensor=(W, H)`")
            yield Frame(img, exposures[k] if k < len(exposures) else None, k,
                        f"{self.path.name}#frame{k}")

    def frame(self, k: int) -> Frame:
        return next(f for i, f in enumerate(self.frames()) if i == k)

    @property
    def has_ground_truth(self) -> bool:
        if not self._has("frames/sharp"):
            return False
        try:
            shape = self._f["frames/sharp"].shape
        except _H5_ERRORS as e:
            raise self._read_error(e) from None
        self._one_per_frame("frames/sharp", 0 if not shape else shape[0], "exposures' sharp "
                            "frames")
        return True

    def ground_truth(self, k: int) -> np.ndarray:
        """(2N+1, H, W[, 3]) float32 latent frames of exposure k."""
        if not self.has_ground_truth:
            raise FormatError("holds no ground truth (frames/sharp)", path=self.path)
        try:
            return np.asarray(self._f["frames/sharp"][k], np.float32)
        except _H5_ERRORS as e:
            raise self._read_error(e) from None

    def contrast(self, k: int) -> float | None:
        if not self._has("frames/contrast"):
            return None
        try:
            return float(self._f["frames/contrast"][k])
        except _H5_ERRORS as e:
            raise self._read_error(e) from None

    @property
    def has_true_motion(self) -> bool:
        """The file stores the simulator's true camera path (``frames/motion``)."""
        return self._has("frames/motion")

    def true_motion(self, k: int) -> np.ndarray | None:
        """(J, 3, 3) float64 homographies of exposure k: middle-frame pixels → pixels at
        exposure fraction ``j/(J−1)`` (see :class:`~trmd_cli.write.H5Writer`); None when the
        file stores none."""
        if not self.has_true_motion:
            return None
        try:
            ds = self._f["frames/motion"]
            shape = ds.shape
            if shape is None or len(shape) != 4 or shape[2:] != (3, 3) or shape[1] < 2:
                raise FormatError(f"frames/motion has shape {shape}, expected (K, J, 3, 3)",
                                  path=self.path, hint="store one (J, 3, 3) camera path per "
                                  "frame, or remove frames/motion")
            if not 0 <= k < shape[0]:
                raise FormatError(f"frames/motion holds {shape[0]} camera paths, none for "
                                  f"frame {k}", path=self.path,
                                  hint="store one camera path per frame, or remove "
                                  "frames/motion")
            h = np.asarray(ds[k], np.float64)
        except _H5_ERRORS as e:
            raise self._read_error(e) from None
        if not np.isfinite(h).all():
            raise FormatError(f"frames/motion of frame {k} holds NaN or infinite values",
                              path=self.path, hint="repair or remove frames/motion")
        return h

    def close(self) -> None:
        f = getattr(self, "_f", None)
        if f is not None:
            f.close()
            self._f = None


def read_hdf5(path: Path, options: ReadOptions) -> HDF5Recording:
    return HDF5Recording(path, options)
