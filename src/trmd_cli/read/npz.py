"""NumPy event files.

``.npz`` keys (first set found): ``x,y,t,p`` | ``xs,ys,ts,ps`` | ``x,y,timestamp,polarity`` |
one structured array (fields t/x/y/p or timestamp/polarity) under any key. Optional:
``width``, ``height`` (or ``sensor_size``), ``exposure_start``, ``exposure_end`` (same unit as t).
``.npy``: a structured array with those fields, or an (E, 4) array in ``--columns`` order
(default t x y p). Integer t = µs, float t = seconds unless ``--time-unit`` says otherwise.
Pickled (object) arrays are refused: loading a pickle can run code.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..events import Exposure, make_stream
from .base import MemoryRecording, ReadOptions
from .units import to_microseconds

__all__ = ["read_npz", "read_npy"]

_KEYSETS = (("x", "y", "t", "p"), ("xs", "ys", "ts", "ps"), ("x", "y", "timestamp", "polarity"),
            ("x", "y", "ts", "p"), ("x", "y", "t", "pol"))


def _load(path: Path):
    try:
        return np.load(path, allow_pickle=False)
    except ValueError as e:
        if "pickle" in str(e).lower():
            raise FormatError("holds pickled objects, which trmd refuses to load (they can "
                              "run code)", path=path,
                              hint="re-save the arrays with numeric dtypes (np.savez)") from None
        raise FormatError(f"not a valid NumPy file: {e}", path=path) from None
    except (zipfile.BadZipFile, OSError, EOFError) as e:
        raise FormatError(f"cannot be read, truncated or corrupt ({e})", path=path) from None


def _get(npz, key: str, path: Path) -> np.ndarray:
    try:
        return npz[key]
    except ValueError as e:
        if "pickle" in str(e).lower():
            raise FormatError(f"key '{key}' holds pickled objects, which trmd refuses to load",
                              path=path, hint="re-save it with a numeric dtype") from None
        raise FormatError(f"key '{key}' cannot be read: {e}", path=path) from None
    except (zipfile.BadZipFile, OSError, EOFError, KeyError) as e:
        raise FormatError(f"key '{key}' cannot be read, truncated or corrupt ({e})",
                          path=path) from None


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
    t = to_microseconds(np.ravel(cols["t"]), options.time_unit)
    x, y = np.ravel(cols["x"]), np.ravel(cols["y"])
    if options.one_based:
        x, y = x.astype(np.int64) - 1, y.astype(np.int64) - 1
    if width is None or height is None:
        warnings.append("the file stores no sensor size: using max+1 of the coordinates "
                        "(pass --sensor WxH to set it)")
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
            raise FormatError(f"no event arrays found (keys: {', '.join(sorted(keys)) or 'none'})",
                              path=path, hint="expected keys x, y, t, p (or xs, ys, ts, ps)")
        width = height = None
        if "width" in keys and "height" in keys:
            width, height = int(_get(npz, "width", path)), int(_get(npz, "height", path))
        elif "sensor_size" in keys:
            size = np.ravel(_get(npz, "sensor_size", path))
            width, height = int(size[0]), int(size[1])
        windows = []
        if "exposure_start" in keys and "exposure_end" in keys:
            s = to_microseconds(np.ravel(_get(npz, "exposure_start", path)), options.time_unit)
            e = to_microseconds(np.ravel(_get(npz, "exposure_end", path)), options.time_unit)
            if len(s) != len(e):
                raise FormatError("exposure_start and exposure_end differ in length", path=path)
            windows = [Exposure(int(a), int(b)) for a, b in zip(s, e)]
    return _build(cols, path, options, "npz", width, height, windows)


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
    else:
        raise FormatError(f"array of shape {arr.shape} is not an event list", path=path,
                          hint="expected (E, 4) columns t x y p or a structured array")
    return _build(cols, path, options, "npy")
