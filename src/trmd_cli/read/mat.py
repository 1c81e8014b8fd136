"""MATLAB ``.mat`` event files, read with scipy (v4–v7.2) or h5py (v7.3).

Layouts understood:

* **eSL-Net** (Wang et al., ECCV 2020; one file per frame): ``section_event_timestamp``,
  ``section_event_x``, ``section_event_y``, ``section_event_polarity`` (each 1×N) and
  ``start_timestamp`` / ``end_timestamp`` (1×1), the frame's exposure window.
* **plain columns**: ``t`` (or ``ts``/``timestamp``/``timestamps``), ``x``, ``y``, ``p`` (or
  ``pol``/``polarity``), each N×1 or 1×N.
* **one matrix**: ``events`` (or ``event``), N×4 with columns t, x, y, p.

Units and conventions:

* time: floating-point values are seconds, integers are microseconds (``--time-unit`` overrides);
  converted to int64 µs and kept absolute — eSL-Net stores seconds since the Unix epoch
  (≈1.6e9 s, resolved to ~0.24 µs by float64), so events and the stored exposure window stay on
  one clock. Conversion splits off whole seconds first so no precision is lost in the product;
* x = column, y = row, 0-based (``--one-based`` for files counting from 1), (0, 0) top-left;
* polarity 1 = ON (+1), 0 or -1 = OFF (-1);
* the file stores no sensor size: ``--sensor`` (or the paired image, see
  :mod:`trmd_cli.read.folders`) gives it; otherwise max+1 with a warning.

Binned files (LEDVDI's ``event_bins``) hold no individual events and are refused with a hint.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..events import Exposure, make_stream
from .base import MemoryRecording, ReadOptions
from .units import UNIT_SCALE_US

__all__ = ["read_mat", "read_mat_window", "seconds_to_us"]

_ESL = ("section_event_timestamp", "section_event_x", "section_event_y",
        "section_event_polarity")
_T = ("t", "ts", "timestamp", "timestamps", "time")
_P = ("p", "pol", "polarity", "polarities")
_WINDOW = ("start_timestamp", "end_timestamp")


def seconds_to_us(t: np.ndarray, unit: str | None) -> np.ndarray:
    """Times → int64 µs: floats are seconds and integers µs unless ``unit`` says otherwise.

    Floats are split into whole and fractional units before scaling, so epoch seconds keep their
    sub-microsecond precision instead of losing it in one large product.
    """
    t = np.asarray(t)
    if t.dtype.kind not in "iuf":
        raise InputError(f"times have type {t.dtype}, expected numbers")
    if unit is None:
        unit = "s" if t.dtype.kind == "f" else "us"
    if unit not in UNIT_SCALE_US:
        raise InputError(f"unknown time unit {unit!r}", hint="use s, ms, us or ns")
    scale = UNIT_SCALE_US[unit]
    if t.dtype.kind in "iu":
        t64 = t.astype(np.int64)
        return t64 // 1000 if unit == "ns" else t64 * int(scale)
    if len(t) and not np.isfinite(t).all():
        bad = int(np.flatnonzero(~np.isfinite(t))[0])
        raise InputError(f"event {bad} has a non-finite time ({t[bad]})")
    t = t.astype(np.float64)
    whole = np.floor(t)
    return (whole.astype(np.int64) * np.int64(round(scale)) if scale >= 1 else
            np.rint(whole * scale).astype(np.int64)) + np.rint((t - whole) * scale).astype(np.int64)


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
        except OSError as e:
            raise FormatError(f"not a readable MATLAB 7.3 file: {e}", path=path) from None
    from . import require

    sio = require("scipy.io", path=path)
    try:
        raw = sio.loadmat(str(path), variable_names=names)
    except (ValueError, TypeError, OSError, EOFError, KeyError, NotImplementedError) as e:
        raise FormatError(f"not a readable .mat file ({e}); truncated or corrupt?",
                          path=path) from None
    except Exception as e:  # noqa: BLE001 - scipy raises many kinds on damaged files
        raise FormatError(f"not a readable .mat file ({type(e).__name__}: {e})",
                          path=path) from None
    return {k: v for k, v in raw.items()
            if not k.startswith("__") and isinstance(v, np.ndarray) and v.dtype.kind in "iufb"}


def _vector(data: dict[str, np.ndarray], name: str, path: Path) -> np.ndarray:
    v = np.asarray(data[name])
    if v.ndim > 2 or (v.ndim == 2 and min(v.shape) > 1):
        raise FormatError(f"variable {name!r} has shape {v.shape}, expected a vector",
                          path=path)
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
    start, end = (seconds_to_us(_vector(data, k, path)[:1], unit)[0] for k in _WINDOW)
    if not end > start:
        raise FormatError(f"stored exposure window [{start}, {end}] µs is empty or reversed",
                          path=path)
    return Exposure(int(start), int(end))


def read_mat(path: Path, options: ReadOptions) -> MemoryRecording:
    """Read a .mat event file (whole, into memory) with its stored exposure window if any.

    Raises:
        FormatError: unreadable file, binned events, no recognised layout (lists the keys).
        InputError: bad values (non-finite times, coordinates outside ``--sensor`` …).
    """
    path = Path(path)
    data = _load(path)
    warnings: list[str] = []
    if all(k in data for k in _ESL):
        cols = {k: _vector(data, name, path) for k, name in zip("txyp", _ESL, strict=True)}
    elif "event_bins" in data:
        raise FormatError("holds binned events ('event_bins', per-pixel polarity sums), not "
                          "individual events", path=path,
                          hint="binned inputs need the voxel path, not an event reader")
    elif _first(data, ("events", "event")) is not None:
        name = _first(data, ("events", "event"))
        m = np.asarray(data[name])
        if m.ndim != 2 or 4 not in m.shape:
            raise FormatError(f"{name!r} has shape {m.shape}, expected N×4 (t, x, y, p)",
                              path=path)
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
    width = height = None
    if options.sensor:
        width, height = options.sensor
    elif len(t_us):
        warnings.append(f"{path.name} stores no sensor size; using {int(np.max(x)) + 1}x"
                        f"{int(np.max(y)) + 1} from the largest coordinates (pass --sensor WxH)")
    stream = make_stream(x, y, t_us, cols["p"], width, height, source=str(path))
    window = _window(data, path, options.time_unit)
    return MemoryRecording(stream, path, "mat", windows=[window] if window else [],
                           warnings=warnings)
