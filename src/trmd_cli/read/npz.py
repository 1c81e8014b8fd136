"""NumPy event files.

``.npz`` keys (first set found): ``x,y,t,p`` | ``xs,ys,ts,ps`` | ``x,y,timestamp,polarity`` |
one structured array (fields t/x/y/p or timestamp/polarity) under any key. Optional:
``width``, ``height`` (or ``sensor_size``), ``exposure_start``, ``exposure_end`` (same unit as t).
``.npy``: a structured array with those fields, or an (E, 4) array in ``columns`` order
(default t x y p; an array of more columns needs ``columns`` naming each, ``_`` for one to skip).
Integer t = µs, float t = seconds unless ``time_unit`` says otherwise. Pickled (object) arrays
are refused: loading a pickle can run code. Event arrays are one value per event: 1-D, or a
column or row vector; a 2-D array of values is refused, not flattened.

An ``.npz`` whose events are four separate arrays (``np.savez``) is streamed, not loaded: its
arrays are read a chunk at a time, straight from their place in the file when stored
uncompressed (memory: one window), decompressed in order otherwise (memory: one chunk, with a
pass from the start for each backward jump); the CRC-32 of every array is checked on the pass
made when the file is opened. Other layouts are loaded whole.
"""

from __future__ import annotations

import struct
import zipfile
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError, InputError, TrmdError
from ..events import Exposure, make_stream
from ..units import times_unit, to_microseconds
from .base import MemoryRecording, ReadOptions
from .chunked import Chunk, ChunkedRecording

__all__ = ["read_npz", "read_npy"]

_KEYSETS = (("x", "y", "t", "p"), ("xs", "ys", "ts", "ps"), ("x", "y", "timestamp", "polarity"),
            ("x", "y", "ts", "p"), ("x", "y", "t", "pol"))


#: hint for files that cannot be decoded
_DAMAGED = "the file may be incomplete or damaged: copy it again or re-save it"


def _load(path: Path):
    try:
        return np.load(path, allow_pickle=False)
    except ValueError as e:
        if "pickle" in str(e).lower():
            raise FormatError("holds pickled objects, which trmd refuses to load (they can "
                              "run code)", path=path,
                              hint="re-save the arrays with numeric dtypes (np.savez)") from None
        raise FormatError(f"not a valid NumPy file: {_first_line(e)}", path=path,
                          hint=_DAMAGED) from None
    except (zipfile.BadZipFile, OSError, EOFError) as e:
        raise FormatError(f"cannot be read, truncated or corrupt ({_first_line(e)})", path=path,
                          hint=_DAMAGED) from None
    except Exception as e:  # noqa: BLE001 - numpy's header parser fails in many ways on damage
        raise FormatError(f"cannot be read ({type(e).__name__}: {_first_line(e)})", path=path,
                          hint=_DAMAGED) from None


def _get(npz, key: str, path: Path) -> np.ndarray:
    try:
        return npz[key]
    except ValueError as e:
        if "pickle" in str(e).lower():
            raise FormatError(f"key '{key}' holds pickled objects, which trmd refuses to load",
                              path=path, hint="re-save it with a numeric dtype") from None
        raise FormatError(f"key '{key}' cannot be read: {_first_line(e)}", path=path,
                          hint=_DAMAGED) from None
    except (zipfile.BadZipFile, OSError, EOFError, KeyError, zlib.error) as e:
        raise FormatError(f"key '{key}' cannot be read, truncated or corrupt ({_first_line(e)})",
                          path=path, hint=_DAMAGED) from None
    except Exception as e:  # noqa: BLE001 - numpy's header parser fails in many ways on damage
        raise FormatError(f"key '{key}' cannot be read ({type(e).__name__}: {_first_line(e)})",
                          path=path, hint=_DAMAGED) from None


def _first_line(e: Exception, limit: int = 120) -> str:
    # numpy quotes whole damaged headers: keep the message to one short line
    text = str(e).splitlines()[0] if str(e) else type(e).__name__
    return text if len(text) <= limit else text[:limit] + "…"


def _structured_columns(arr: np.ndarray) -> dict[str, np.ndarray] | None:
    names = arr.dtype.names or ()
    alias = {"t": ("t", "ts", "timestamp"), "x": ("x", "xs"), "y": ("y", "ys"),
             "p": ("p", "ps", "polarity", "pol")}
    out = {}
    for k, opts in alias.items():
        hit = next((n for n in opts if n in names), None)
        if hit is None:
            return None
        out[k] = arr[hit]
    return out


def _vector(arr: np.ndarray, name: str, path: Path) -> np.ndarray:
    """One value per event: a 1-D array, or a column or row vector (never a 2-D table
    flattened into one, which would mix its columns into a single event list)."""
    a = np.asarray(arr)
    if a.ndim == 1:
        return a
    if a.ndim == 0 or sum(d > 1 for d in a.shape) > 1:
        raise FormatError(f"'{name}' has shape {a.shape}, expected one value per event (1-D)",
                          path=path, hint="store each of x, y, t, p as a 1-D array")
    return a.reshape(-1)


def _build(cols: dict, path: Path, options: ReadOptions, fmt: str, width=None, height=None,
           windows=()) -> MemoryRecording:
    warnings = []
    if options.sensor is not None:
        width, height = options.sensor
    elif (width is None or height is None) and options.frame_size is not None:
        width, height = options.frame_size
    cols = {k: _vector(v, k, path) for k, v in cols.items()}
    t = to_microseconds(cols["t"], options.time_unit)
    x, y = cols["x"], cols["y"]
    if options.one_based:
        x, y = x.astype(np.int64) - 1, y.astype(np.int64) - 1
    if width is None or height is None:
        warnings.append("the file stores no sensor size: using max+1 of the coordinates "
                        "(pass `sensor=(W, H)` to set it)")
    try:
        stream = make_stream(x, y, t, cols["p"], width, height, source=str(path))
    except InputError as e:
        raise InputError(e.detail, path=path, hint=e.hint) from None
    return MemoryRecording(stream, path, fmt, windows=windows, warnings=warnings,
                           times_unit=times_unit(cols["t"].dtype, options.time_unit))


def read_npz(path: Path, options: ReadOptions) -> MemoryRecording | NpzRecording:
    with _load(path) as npz:
        keys = set(npz.files)
        cols = None
        for ks in _KEYSETS:
            if set(ks) <= keys:
                members = _members(path, ks)
                if members is not None:
                    return NpzRecording(path, options, members, *_extras(npz, keys, path,
                                                                         options))
                cols = dict(zip("xytp", (_get(npz, k, path) for k in ks)))
                break
        if cols is None:
            for k in npz.files:
                arr = _get(npz, k, path)
                if arr.dtype.names:
                    cols = _structured_columns(arr)
                    if cols:
                        break
        if cols is None:
            if "event_bins" in keys:
                from .bins import BINNED_HINT

                raise FormatError("holds binned events ('event_bins', per-pixel polarity sums), "
                                  "not individual events", path=path, hint=BINNED_HINT)
            raise FormatError(f"no event arrays found (keys: {', '.join(sorted(keys)) or 'none'})",
                              path=path, hint="expected keys x, y, t, p (or xs, ys, ts, ps)")
        width, height, windows = _extras(npz, keys, path, options)
    return _build(cols, path, options, "npz", width, height, windows)


def _extras(npz, keys: set[str], path: Path, options: ReadOptions):
    """(width, height, stored windows) from the small arrays beside the events."""
    width = height = None
    if "width" in keys and "height" in keys:
        width = _size(_get(npz, "width", path), "width", path)
        height = _size(_get(npz, "height", path), "height", path)
    elif "sensor_size" in keys:
        size = np.ravel(_get(npz, "sensor_size", path))
        if len(size) < 2:
            raise FormatError(f"sensor_size holds {len(size)} value(s), expected 2 (W, H)",
                              path=path, hint="pass `sensor=(W, H)`")
        width, height = (_size(v, name, path)
                         for v, name in zip(size[:2], ("width", "height"), strict=True))
    windows = []
    if "exposure_start" in keys and "exposure_end" in keys:
        windows = _windows(_get(npz, "exposure_start", path), _get(npz, "exposure_end", path),
                           options, path)
    return width, height, windows


# -- streaming the four event arrays of an .npz -------------------------------------------------

#: events per chunk when streaming an .npz (13 bytes each as stored)
NPZ_CHUNK_EVENTS = 1 << 22


class _Member:
    """One event array of an .npz as stored: where its data start, how it is compressed."""

    def __init__(self, info: zipfile.ZipInfo, key: str, dtype: np.dtype, count: int,
                 data_offset: int, header_bytes: bytes) -> None:
        self.info, self.key, self.dtype, self.count = info, key, dtype, count
        self.data_offset = data_offset  # in the .npz when stored; in the member when deflated
        self.header_bytes = header_bytes  # the .npy header, for the CRC
        self.stored = info.compress_type == zipfile.ZIP_STORED


def _members(path: Path, keys: tuple[str, ...]) -> dict[str, _Member] | None:
    """The four event arrays, when each is a plain 1-D (or vector) array of numbers in C order
    and all have one length: they can be streamed. None: load them whole (the old way, which
    also words any damage)."""
    out: dict[str, _Member] = {}
    try:
        with zipfile.ZipFile(path) as zf, open(path, "rb") as raw:
            for name, key in zip("xytp", keys, strict=True):
                info = zf.getinfo(f"{key}.npy")
                if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
                    return None
                with zf.open(info) as fh:
                    version = np.lib.format.read_magic(fh)
                    shape, fortran, dtype = (np.lib.format.read_array_header_1_0(fh)
                                             if version == (1, 0) else
                                             np.lib.format.read_array_header_2_0(fh))
                    header_len = fh.tell()
                if dtype.hasobject or dtype.names or dtype.kind not in "iufb" or (
                        len(shape) != 1 and (fortran or sum(d > 1 for d in shape) > 1
                                             or len(shape) == 0)):
                    return None
                count = int(np.prod(shape))
                if header_len + count * dtype.itemsize != info.file_size:
                    return None
                offset = header_len
                if info.compress_type == zipfile.ZIP_STORED:
                    raw.seek(info.header_offset)
                    local = raw.read(30)
                    if len(local) < 30 or local[:4] != b"PK\x03\x04":
                        return None
                    name_len, extra_len = struct.unpack("<HH", local[26:30])
                    offset = info.header_offset + 30 + name_len + extra_len + header_len
                    raw.seek(offset - header_len)
                    head = raw.read(header_len)
                else:
                    with zf.open(info) as fh:
                        head = fh.read(header_len)
                out[name] = _Member(info, key, dtype, count, offset, head)
    except Exception:  # noqa: BLE001 - anything odd: the whole-file path says what is wrong
        return None
    if len({m.count for m in out.values()}) != 1:
        return None
    return out


class NpzRecording(ChunkedRecording):
    """An .npz of four event arrays, read a chunk at a time (see the module docstring)."""

    size_guess_note = ("the file stores no sensor size: using max+1 of the coordinates "
                       "(pass `sensor=(W, H)` to set it)")

    def __init__(self, path: Path, options: ReadOptions, members: dict[str, _Member],
                 width: int | None, height: int | None, windows, *,
                 chunk_events: int | None = None) -> None:
        if options.sensor is not None:
            width, height = options.sensor
        elif (width is None or height is None) and options.frame_size is not None:
            width, height = options.frame_size
        for name, size in (("width", width), ("height", height)):
            if size is not None and not 0 < size <= 65535:
                raise InputError(f"sensor {name} {size!r} is not a whole number in 1..65535",
                                 path=path, hint="pass `sensor=(W, H)`")
        super().__init__(path, "npz", width, height)
        self._members = members
        self._options = options
        self._chunk = int(NPZ_CHUNK_EVENTS if chunk_events is None else chunk_events)
        self._n = members["t"].count
        self._windows = list(windows)
        self._unit = options.time_unit
        self.times_unit = times_unit(members["t"].dtype, options.time_unit)
        self._stored = all(m.stored for m in members.values())
        self._crc: dict[str, int] | None = None
        try:
            self._crc = {k: zlib.crc32(m.header_bytes) for k, m in members.items()}
            self._build_index()
        except TrmdError:
            self._crc = None
            self._check_crc(None)  # damage the checksums see is named as damage
            raise
        crc, self._crc = self._crc, None
        self._check_crc(crc)

    # -- decoding ---------------------------------------------------------------------------

    def _decode(self, start: int = 0, resume: Any = None) -> Iterator[Chunk]:
        step = self._chunk
        if self._stored:
            with open(self.path, "rb") as fh:
                for k in range(start, (self._n + step - 1) // step):
                    lo, hi = k * step, min(self._n, (k + 1) * step)
                    cols = {}
                    for name, m in self._members.items():
                        fh.seek(m.data_offset + lo * m.dtype.itemsize)
                        cols[name] = self._column(name, fh.read((hi - lo) * m.dtype.itemsize))
                    yield self._chunk_of(k, lo, cols)
            return
        with zipfile.ZipFile(self.path) as zf:
            handles = {name: zf.open(m.info) for name, m in self._members.items()}
            try:
                for name, fh in handles.items():
                    fh.read(self._members[name].data_offset)  # past the .npy header
                for k in range((self._n + step - 1) // step):
                    lo, hi = k * step, min(self._n, (k + 1) * step)
                    cols = {name: self._column(name, fh.read(
                        (hi - lo) * self._members[name].dtype.itemsize))
                        for name, fh in handles.items()}
                    if k >= start:
                        yield self._chunk_of(k, lo, cols)
            except (zipfile.BadZipFile, zlib.error, OSError, EOFError) as e:
                raise FormatError(f"cannot be read, truncated or corrupt ({_first_line(e)})",
                                  path=self.path, hint=_DAMAGED) from None
            finally:
                for fh in handles.values():
                    fh.close()

    def _column(self, name: str, data: bytes) -> np.ndarray:
        m = self._members[name]
        if self._crc is not None:
            self._crc[name] = zlib.crc32(data, self._crc[name])
        if len(data) % m.dtype.itemsize:
            raise FormatError(f"key '{m.key}' cannot be read, truncated or corrupt",
                              path=self.path, hint=_DAMAGED)
        arr = np.frombuffer(data, m.dtype)
        return arr if m.dtype.isnative else arr.astype(m.dtype.newbyteorder("="))

    def _chunk_of(self, k: int, first: int, cols: dict[str, np.ndarray]) -> Chunk:
        """Validate one chunk (as :func:`make_stream` does a whole file) in library units."""
        try:
            t = to_microseconds(cols["t"], self._unit, first=first)
            x, y = cols["x"], cols["y"]
            if self._options.one_based:
                x, y = x.astype(np.int64) - 1, y.astype(np.int64) - 1
            s = make_stream(x, y, t, cols["p"], self.width, self.height, source=str(self.path),
                            first=first)
        except InputError as e:
            raise InputError(e.detail, path=self.path, hint=e.hint) from None
        return Chunk(k, s.x, s.y, s.t, s.p, resume=k if self._stored else None)

    def _time_error(self, index: int) -> InputError:
        return InputError(f"event times are not sorted (event {index} goes back in time)",
                          path=self.path, hint="sort the events by time first")

    def _check_crc(self, crc: dict[str, int] | None) -> None:
        """Compare each array's CRC-32 with the archive's: ``crc`` as the index pass computed
        it while reading everything; None: read the arrays again to compute it (a value was
        refused half way through: if the bytes are damaged, that is what to say)."""
        for name, m in self._members.items():
            got = None if crc is None else crc[name]
            if got is None:
                try:
                    got = self._member_crc(m)
                except (zipfile.BadZipFile, zlib.error, OSError, EOFError):
                    got = -1
            if got != m.info.CRC:
                raise FormatError(f"key '{m.key}' cannot be read, truncated or corrupt (Bad "
                                  f"CRC-32 for file '{m.key}.npy')", path=self.path,
                                  hint=_DAMAGED)

    def _member_crc(self, m: _Member) -> int:
        block = 1 << 24
        with zipfile.ZipFile(self.path) as zf, zf.open(m.info) as fh:
            if not m.stored:
                while fh.read(block):  # ZipExtFile checks the CRC at the end itself
                    pass
                return m.info.CRC
        crc, left = zlib.crc32(m.header_bytes), m.count * m.dtype.itemsize
        with open(self.path, "rb") as raw:
            raw.seek(m.data_offset)
            while left:
                data = raw.read(min(block, left))
                if not data:
                    return -1
                crc, left = zlib.crc32(data, crc), left - len(data)
        return crc

    def stored_windows(self) -> list[Exposure]:
        return list(self._windows)


def _size(value: np.ndarray, name: str, path: Path) -> int:
    v = np.asarray(value)
    if v.size != 1 or v.dtype.kind not in "iuf" or not float(v.ravel()[0]).is_integer():
        raise FormatError(f"'{name}' is {v.ravel()[:4].tolist()}, expected one whole number",
                          path=path, hint="pass `sensor=(W, H)`")
    return int(v.ravel()[0])


def _windows(start: np.ndarray, end: np.ndarray, options: ReadOptions,
             path: Path) -> list[Exposure]:
    """Stored exposure windows, checked: same count, finite, each end after its start."""
    try:
        s = to_microseconds(np.ravel(start), options.time_unit)
        e = to_microseconds(np.ravel(end), options.time_unit)
    except InputError as err:
        raise FormatError(f"exposure_start/exposure_end: {err.detail}", path=path,
                          hint="repair the stored windows, or give `exposure=(T0, T1)`") from None
    if len(s) != len(e):
        raise FormatError(f"exposure_start has {len(s)} values but exposure_end {len(e)}",
                          path=path, hint="store one start and one end per window")
    bad = np.flatnonzero(e <= s)
    if len(bad):
        i = int(bad[0])
        raise FormatError(f"stored exposure window {i} [{s[i]}, {e[i]}] µs is empty or reversed",
                          path=path, hint="repair the stored windows, or give `exposure=(T0, T1)`")
    return [Exposure(int(a), int(b)) for a, b in zip(s, e, strict=True)]


def read_npy(path: Path, options: ReadOptions) -> MemoryRecording:
    arr = _load(path)
    if arr.dtype.names:
        cols = _structured_columns(arr)
        if cols is None:
            raise FormatError(f"structured array fields {arr.dtype.names} lack t/x/y/p",
                              path=path, hint="name the fields t, x, y, p")
    elif arr.ndim == 2 and arr.shape[1] >= 4:
        order = options.columns or ("t", "x", "y", "p")
        if len(order) != arr.shape[1]:
            raise FormatError(f"array of shape {arr.shape} has {arr.shape[1]} columns but "
                              f"{len(order)} are named ({' '.join(order)})"
                              + (": the others would be dropped" if arr.shape[1] > len(order)
                                 else ""), path=path,
                              hint="pass `columns` naming every column (`_` for one to skip), "
                                   "e.g. `columns=t,x,y,p,_`")
        cols = {name: arr[:, i] for i, name in enumerate(order) if name != "_"}
    elif arr.ndim in (3, 4):
        from .bins import BINNED_HINT

        raise FormatError(f"array of shape {arr.shape} is not an event list but looks like "
                          "binned events (per-pixel counts)", path=path, hint=BINNED_HINT)
    else:
        raise FormatError(f"array of shape {arr.shape} is not an event list", path=path,
                          hint="expected (E, 4) columns t x y p or a structured array")
    return _build(cols, path, options, "npy")
