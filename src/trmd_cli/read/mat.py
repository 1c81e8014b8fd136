"""MATLAB ``.mat`` event files: level 5 (v6, v7) parsed here with numpy, v7.3 read with h5py.

Layouts understood:

* **eSL-Net** (Wang et al., ECCV 2020; one file per frame): ``section_event_timestamp``,
  ``section_event_x``, ``section_event_y``, ``section_event_polarity`` (each 1×N) and
  ``start_timestamp`` / ``end_timestamp`` (1×1), the frame's exposure window.
* **plain columns**: ``t`` (or ``ts``/``timestamp``/``timestamps``), ``x``, ``y``, ``p`` (or
  ``pol``/``polarity``), each N×1 or 1×N.
* **one matrix**: ``events`` (or ``event``), N×4 with columns t, x, y, p.

Units and conventions:

* time: floating-point values are seconds, integers are microseconds (``time_unit`` overrides);
  converted to int64 µs and kept absolute — eSL-Net stores seconds since the Unix epoch
  (≈1.6e9 s, resolved to ~0.24 µs by float64), so events and the stored exposure window stay on
  one clock. Conversion splits off whole seconds first so no precision is lost in the product;
* x = column, y = row, 0-based (``one_based=True`` for files counting from 1), (0, 0) top-left;
* polarity 1 = ON (+1), 0 or -1 = OFF (-1);
* the file stores no sensor size: ``sensor`` (or the paired image, see
  :mod:`trmd_cli.read.folders`) gives it; otherwise max+1 with a warning.

Binned files (LEDVDI's ``event_bins``) hold no individual events: this reader refuses them with
a pointer to the binned frame source (:mod:`trmd_cli.read.bins`), which reads them;
:func:`mat_variable_names` lets it recognise them without decoding the data.
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..events import Exposure, make_stream
from ..units import UNIT_SCALE_US
from .base import MemoryRecording, ReadOptions

__all__ = ["read_mat", "read_mat_window", "mat_variable_names", "seconds_to_us"]

_ESL = ("section_event_timestamp", "section_event_x", "section_event_y",
        "section_event_polarity")
_T = ("t", "ts", "timestamp", "timestamps", "time")
_P = ("p", "pol", "polarity", "polarities")
_WINDOW = ("start_timestamp", "end_timestamp")


#: hint for files that cannot be decoded
_DAMAGED = "the file may be incomplete or damaged: copy it again or re-save it"


def seconds_to_us(t: np.ndarray, unit: str | None) -> np.ndarray:
    """Times → int64 µs: floats are seconds and integers µs unless ``unit`` says otherwise.

    Floats are split into whole and fractional units before scaling, so epoch seconds keep their
    sub-microsecond precision instead of losing it in one large product.
    """
    t = np.asarray(t)
    if t.dtype.kind not in "iuf":
        raise InputError(f"times have type {t.dtype}, expected numbers",
                         hint="store times as integer microseconds or float seconds")
    if unit is None:
        unit = "s" if t.dtype.kind == "f" else "us"
    if unit not in UNIT_SCALE_US:
        raise InputError(f"unknown time unit {unit!r}", hint="use s, ms, us or ns")
    scale = UNIT_SCALE_US[unit]
    if len(t):
        # one reduction each, no mask (a window's times are converted every time it is
        # read): NaN or ±∞ make the extremes non-finite
        low, high = float(t.min()), float(t.max())
        if not (np.isfinite(low) and np.isfinite(high)):
            finite = t[np.isfinite(t)]
            if len(finite):  # a unit mistake is said first, as for finite times
                _refuse_out_of_range(float(finite.min()), float(finite.max()), unit, scale)
            bad = int(np.flatnonzero(~np.isfinite(t))[0])
            raise InputError(f"event {bad} has a non-finite time ({t[bad]})",
                             hint="remove or repair the broken events")
        _refuse_out_of_range(low, high, unit, scale)
    if t.dtype.kind in "iu":
        t64 = t.astype(np.int64)
        return t64 // 1000 if unit == "ns" else t64 * int(scale)
    t = t.astype(np.float64, copy=False)
    whole = np.floor(t)
    frac = np.subtract(t, whole)
    frac *= scale
    np.rint(frac, out=frac)
    if scale >= 1:
        out = whole.astype(np.int64)
        out *= np.int64(round(scale))
    else:
        whole *= scale
        out = np.rint(whole, out=whole).astype(np.int64)
    out += frac.astype(np.int64)
    return out


def _refuse_out_of_range(low: float, high: float, unit: str, scale: float) -> None:
    """Refuse times beyond ±2**62 µs (≈146 000 years): a unit mistake, and int64 would
    overflow."""
    top = max(abs(low), abs(high))
    if top * scale >= 2.0**62:
        raise InputError(f"times up to {top:g} {unit} are out of range", hint="check `time_unit`")


def _load(path: Path, names: list[str] | None = None) -> dict[str, np.ndarray]:
    """Numeric variables of a .mat file as flat-or-2-D arrays (v7.3 transposed back)."""
    with open(path, "rb") as fh:
        head = fh.read(128)
    if head.startswith(b"MATLAB 7.3"):
        import h5py

        try:
            with h5py.File(path, "r") as f:
                keys = [k for k in f.keys() if isinstance(f[k], h5py.Dataset)]
                keys = [k for k in keys if names is None or k in names]
                return {k: np.asarray(f[k][()]).T for k in keys}
        except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
            raise FormatError(f"not a readable MATLAB 7.3 file: {e}", path=path,
                              hint=_DAMAGED) from None
    try:
        return _read_v5(path.read_bytes(), names)
    except _Damaged as e:
        raise FormatError(f"not a readable .mat file ({e}); truncated or corrupt?", path=path,
                          hint=_DAMAGED) from None


# -- MAT-file level 5 (v6/v7), numeric variables ------------------------------------------------
# Parsed here rather than by scipy.io.loadmat: scipy's compiled reader crashes the process
# (SIGSEGV) on some damaged files, e.g. an unknown data type in a variable's header.

#: MAT data types → numpy, for the data elements of numeric arrays
_MI_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 9: "f8", 12: "i8",
             13: "u8"}
#: numeric MAT array classes (double, single, int8 … uint64); the others (cell, struct, char,
#: sparse, objects) hold no events and are skipped
_MX_CLASSES = frozenset(range(6, 16))
_MI_MATRIX, _MI_COMPRESSED = 14, 15


class _Damaged(Exception):
    """The bytes do not follow the MAT-file level 5 layout."""


def _elements(buf: bytes | memoryview, pos: int, end: int, order: str):
    """(type, data) of each data element in ``buf[pos:end]``; the data are views of ``buf``
    (copying a variable's bytes out of the file's cost as much as parsing it)."""
    buf = memoryview(buf)
    while pos + 8 <= end:
        typ, nbytes = np.frombuffer(buf, order + "u4", 2, pos)
        typ, nbytes = int(typ), int(nbytes)
        if typ >> 16:  # small element: size in the upper half, data in the tag's second word
            typ, nbytes, start = typ & 0xFFFF, typ >> 16, pos + 4
            stop = start + nbytes
            if nbytes > 4:
                raise _Damaged(f"small element of {nbytes} bytes at byte {pos}")
            nxt = pos + 8
        else:
            start = pos + 8
            stop = start + nbytes
            # compressed elements are not padded; the others end on an 8-byte boundary
            nxt = stop if typ == _MI_COMPRESSED else start + -(-nbytes // 8) * 8
        if stop > end:
            raise _Damaged(f"element at byte {pos} runs past its end ({nbytes} bytes)")
        yield typ, buf[start:stop]
        pos = nxt
    if pos < end and bytes(buf[pos:end]).strip(b"\x00"):
        raise _Damaged(f"{end - pos} stray bytes at byte {pos}")


def _matrix(data: bytes, order: str) -> tuple[str, np.ndarray | None]:
    """(name, array or None when not a real numeric array) of one miMATRIX element."""
    parts = list(_elements(data, 0, len(data), order))
    if (len(parts) < 3 or parts[0][0] != 6 or len(parts[0][1]) != 8 or parts[1][0] != 5
            or len(parts[1][1]) % 4):
        raise _Damaged("a variable header lacks its flags, dimensions or name")
    flags = int(np.frombuffer(parts[0][1], order + "u4", 1)[0])
    dims = np.frombuffer(parts[1][1], order + "i4")
    name = bytes(parts[2][1]).decode("latin-1")
    if (dims < 0).any():
        raise _Damaged(f"variable {name!r} has negative dimensions {dims.tolist()}")
    mx, is_complex = flags & 0xFF, bool(flags & 0x800)
    if mx not in _MX_CLASSES or is_complex:
        return name, None
    if len(parts) < 4 or parts[3][0] not in _MI_TYPES:
        raise _Damaged(f"variable {name!r} has no numeric data")
    raw = parts[3][1]
    dtype = np.dtype(order + _MI_TYPES[parts[3][0]])
    if len(raw) % dtype.itemsize:
        raise _Damaged(f"variable {name!r}: {len(raw)} bytes of {dtype.name}")
    values = np.frombuffer(raw, dtype)
    if values.size != int(np.prod(dims.astype(np.int64))):
        raise _Damaged(f"variable {name!r} holds {values.size} values for dimensions "
                       f"{dims.tolist()}")
    # in the type stored, as scipy.io.loadmat gives them (MATLAB stores whole doubles as ints)
    return name, values.reshape(dims, order="F")


def _read_v5(buf: bytes, names: list[str] | None) -> dict[str, np.ndarray]:
    """Numeric variables of a level-5 MAT-file (as scipy.io.loadmat would give them)."""
    if len(buf) < 128:
        raise _Damaged("shorter than the 128-byte header")
    order = {b"IM": "<", b"MI": ">"}.get(buf[126:128])
    if order is None:
        raise _Damaged("no byte-order mark in the header")
    out: dict[str, np.ndarray] = {}
    for typ, data in _elements(buf, 128, len(buf), order):
        if typ == _MI_COMPRESSED:
            try:
                data = zlib.decompressobj().decompress(data)
            except zlib.error as e:
                raise _Damaged(f"compressed variable: {e}") from None
            inner = list(_elements(data, 0, len(data), order))
            if not inner:
                raise _Damaged("empty compressed variable")
            typ, data = inner[0]
        if typ != _MI_MATRIX:
            continue
        name, array = _matrix(data, order)
        if array is not None and (names is None or name in names):
            out[name] = array
    return out


def mat_variable_names(path: str | Path) -> list[str]:
    """Names of a .mat file's variables, without decoding their data: a compressed variable is
    inflated only as far as its name. Cheap enough to sniff a file with; a damaged file gives
    the names found before the damage (reading it then reports the damage).

    Raises:
        FormatError: not a MAT-file (level 5 or v7.3).
    """
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(128)
        if head.startswith(b"MATLAB 7.3"):
            import h5py

            try:
                with h5py.File(path, "r") as f:
                    return [k for k in f.keys() if isinstance(f[k], h5py.Dataset)]
            except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
                raise FormatError(f"not a readable MATLAB 7.3 file: {e}", path=path,
                                  hint=_DAMAGED) from None
        order = {b"IM": "<", b"MI": ">"}.get(head[126:128]) if len(head) == 128 else None
        if order is None:
            raise FormatError("not a MAT-file (no level 5 header)", path=path, hint=_DAMAGED)
        names: list[str] = []
        pos = 128
        while True:
            fh.seek(pos)
            tag = fh.read(8)
            if len(tag) < 8:
                return names
            typ, nbytes = (int(v) for v in np.frombuffer(tag, order + "u4", 2))
            if typ >> 16:  # a small element: no variable
                pos += 8
                continue
            if typ == _MI_COMPRESSED:
                inflate = zlib.decompressobj()
                try:
                    data = inflate.decompress(fh.read(min(nbytes, 1 << 12)), 1 << 10)
                except zlib.error:
                    return names
                if len(data) < 8:
                    return names
                typ = int(np.frombuffer(data, order + "u4", 1)[0])
                payload = data[8:]
                pos += 8 + nbytes
            else:
                payload = fh.read(min(nbytes, 1 << 10))
                pos += 8 + -(-nbytes // 8) * 8
            if typ == _MI_MATRIX:
                name = _matrix_name(payload, order)
                if name is None:
                    return names
                names.append(name)


def _matrix_name(payload: bytes, order: str) -> str | None:
    """The name of a miMATRIX element from the first bytes of its data, or None."""
    parts = []
    try:
        for part in _elements(payload, 0, len(payload), order):
            parts.append(part)
            if len(parts) == 3:
                break
    except _Damaged:
        pass
    if len(parts) < 3 or parts[0][0] != 6 or parts[1][0] != 5:
        return None
    return bytes(parts[2][1]).decode("latin-1")


def _vector(data: dict[str, np.ndarray], name: str, path: Path) -> np.ndarray:
    v = np.asarray(data[name])
    if v.ndim > 2 or (v.ndim == 2 and min(v.shape) > 1):
        raise FormatError(f"variable {name!r} has shape {v.shape}, expected a vector",
                          path=path, hint="store one value per event (1×N or N×1)")
    return v.ravel()


def _first(data: dict[str, np.ndarray], names: tuple[str, ...]) -> str | None:
    lower = {k.lower(): k for k in data}
    return next((lower[n] for n in names if n in lower), None)


def read_mat_window(path: Path, options: ReadOptions | None = None) -> Exposure | None:
    """The stored exposure window (eSL-Net ``start_timestamp``/``end_timestamp``) without
    loading the events; None if the file stores none."""
    path = Path(path)
    data = _load(path, list(_WINDOW))
    return _window(data, path, (options or ReadOptions()).time_unit)


def _window(data: dict[str, np.ndarray], path: Path, unit: str | None) -> Exposure | None:
    if not all(k in data for k in _WINDOW):
        return None
    values = [_vector(data, k, path)[:1] for k in _WINDOW]
    if any(len(v) == 0 for v in values):
        raise FormatError("start_timestamp or end_timestamp is empty", path=path,
                          hint="repair them, or give `exposure=(T0, T1)`")
    start, end = (seconds_to_us(v, unit)[0] for v in values)
    if not end > start:
        raise FormatError(f"stored exposure window [{start}, {end}] µs is empty or reversed",
                          path=path, hint="repair start_timestamp/end_timestamp, or give "
                                          "`exposure=(T0, T1)`")
    return Exposure(int(start), int(end))


def read_mat(path: Path, options: ReadOptions) -> MemoryRecording:
    """Read a .mat event file (whole, into memory) with its stored exposure window if any.

    Raises:
        FormatError: unreadable file, binned events, no recognised layout (lists the keys).
        InputError: bad values (non-finite times, coordinates outside ``sensor`` …).
    """
    path = Path(path)
    data = _load(path)
    warnings: list[str] = []
    if all(k in data for k in _ESL):
        cols = {k: _vector(data, name, path) for k, name in zip("txyp", _ESL, strict=True)}
    elif "event_bins" in data:
        from .bins import BINNED_HINT

        raise FormatError("holds binned events ('event_bins', per-pixel polarity sums), not "
                          "individual events", path=path, hint=BINNED_HINT)
    elif _first(data, ("events", "event")) is not None:
        name = _first(data, ("events", "event"))
        m = np.asarray(data[name])
        if m.ndim != 2 or 4 not in m.shape:
            raise FormatError(f"{name!r} has shape {m.shape}, expected N×4 (t, x, y, p)",
                              path=path, hint="store the events as an N×4 matrix t, x, y, p")
        m = m if m.shape[1] == 4 else m.T
        cols = dict(zip("txyp", m.T, strict=True))
    elif all(_first(data, names) for names in (_T, ("x",), ("y",), _P)):
        cols = {k: _vector(data, _first(data, names), path)
                for k, names in zip("txyp", (_T, ("x",), ("y",), _P), strict=True)}
    else:
        keys = ", ".join(sorted(data)) or "none"
        raise FormatError(f"no events found (numeric variables: {keys})", path=path,
                          hint="expected eSL-Net section_event_* keys, t/x/y/p vectors, or an "
                               "N×4 'events' matrix")
    t_us = seconds_to_us(cols["t"], options.time_unit)
    x, y = cols["x"], cols["y"]
    if options.one_based:
        x, y = x - 1, y - 1
    width, height = options.sensor or options.frame_size or (None, None)
    stream = make_stream(x, y, t_us, cols["p"], width, height, source=str(path))
    if width is None and len(stream):
        warnings.append(f"{path.name} stores no sensor size; using {stream.width}x"
                        f"{stream.height} from the largest coordinates (pass `sensor=(W, H)`)")
    window = _window(data, path, options.time_unit)
    return MemoryRecording(stream, path, "mat", windows=[window] if window else [],
                           warnings=warnings, times_unit=options.time_unit or "s")
