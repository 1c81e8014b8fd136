"""NumPy event files.

``.npz`` keys (first set found): ``x,y,t,p`` | ``xs,ys,ts,ps`` | ``x,y,timestamp,polarity`` |
one structured array (fields t/x/y/p or timestamp/polarity) under any key. Optional:
``width``, ``height`` (or ``sensor_size``), ``exposure_start``, ``exposure_end`` (same unit as t).
``.npy``: a structured array with those fields, or an (E, 4) array in ``columns`` order
(default t x y p). Integer t = µs, float t = seconds unless ``time_unit`` says otherwise.
Pickled (object) arrays are refused: loading a pickle can run code.
"""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..events import Exposure, make_stream
from .base import MemoryRecording, ReadOptions
from .units import to_microseconds

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


def _build(cols: dict, path: Path, options: ReadOptions, fmt: str, width=None, height=None,
           windows=()) -> MemoryRecording:
    warnings = []
    if options.sensor is not None:
        width, height = options.sensor
    elif (width is None or height is None) and options.frame_size is not None:
        width, height = options.frame_size
    t = to_microseconds(np.ravel(cols["t"]), options.time_unit)
    x, y = np.ravel(cols["x"]), np.ravel(cols["y"])
    if options.one_based:
        x, y = x.astype(np.int64) - 1, y.astype(np.int64) - 1
    if width is None or height is None:
        warnings.append("the file stores no sensor size: using max+1 of the coordinates "
                        "(pass `sensor=(W, H)` to set it)")
    try:
        stream = make_stream(x, y, t, np.ravel(cols["p"]), width, height, source=str(path))
    except InputError as e:
        raise InputError(e.detail, path=path, hint=e.hint) from None
    return MemoryRecording(stream, path, fmt, windows=windows, warnings=warnings)


def read_npz(path: Path, options: ReadOptions) -> MemoryRecording:
    with _load(path) as npz:
        keys = set(npz.files)
        cols = None
        for ks in _KEYSETS:
            if set(ks) <= keys:
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
    return _build(cols, path, options, "npz", width, height, windows)


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
        cols = {name: arr[:, i] for i, name in enumerate(order) if name != "_"}
    elif arr.ndim in (3, 4):
        from .bins import BINNED_HINT

        raise FormatError(f"array of shape {arr.shape} is not an event list but looks like "
                          "binned events (per-pixel counts)", path=path, hint=BINNED_HINT)
    else:
        raise FormatError(f"array of shape {arr.shape} is not an event list", path=path,
                          hint="expected (E, 4) columns t x y p or a structured array")
    return _build(cols, path, options, "npy")
