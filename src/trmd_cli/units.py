"""Time-unit conversion, done once, on the way in."""

from __future__ import annotations

import numpy as np

from .errors import InputError

__all__ = ["to_microseconds", "collapsed_times", "UNIT_SCALE_US"]

#: microseconds per unit
UNIT_SCALE_US = {"s": 1_000_000, "ms": 1_000, "us": 1, "ns": 0.001}


def times_unit(dtype, unit: str | None = None) -> str:
    """The unit a file's times stored as ``dtype`` are read in: ``unit`` when given, else
    seconds for floats and µs for integers."""
    return unit if unit is not None else ("s" if np.dtype(dtype).kind == "f" else "us")


def to_microseconds(t: np.ndarray, unit: str | None, first: int = 0) -> np.ndarray:
    """Convert times to int64 µs. ``unit=None``: integers are µs, floats are seconds.
    Nanoseconds are floored to whole µs; other units are rounded to the nearest µs.

    Float seconds are converted relative to nothing (absolute): float64 resolves ~0.24 µs at
    1.6e9 s, so epoch-based timestamps survive to the microsecond. ``first``: the file's index
    of ``t[0]``, for messages.
    """
    t = np.asarray(t)
    unit = times_unit(t.dtype, unit)
    if unit not in UNIT_SCALE_US:
        raise InputError(f"unknown time unit {unit!r}", hint="use s, ms, us or ns")
    if t.dtype.kind not in "iuf":
        raise InputError(f"times have type {t.dtype}, expected numbers",
                         hint="store times as integer microseconds or float seconds")
    if t.dtype.kind == "f" and len(t) and not np.isfinite(t).all():
        bad = int(np.flatnonzero(~np.isfinite(t))[0])
        raise InputError(f"event {first + bad} has a non-finite time ({t[bad]})",
                         hint="remove or repair the broken rows")
    scale = UNIT_SCALE_US[unit]
    # ±2**62 µs is ≈146 000 years: beyond it a value is a unit mistake, and int64 overflows
    top = max(abs(float(t.max())), abs(float(t.min()))) if len(t) else 0.0
    if top * scale >= 2.0**62:
        raise InputError(f"times up to {top:g} {unit} are out of range", hint="check `time_unit`")
    if unit == "us" and t.dtype.kind in "iu":
        return t.astype(np.int64, copy=False)
    if unit == "ns":
        # whole µs is the event stream's resolution: nanoseconds are floored to it, written as
        # integers or as floats alike (the same time gives the same µs in every format)
        if t.dtype.kind in "iu":
            return t.astype(np.int64) // 1000
        return np.floor(t.astype(np.float64) / 1000.0).astype(np.int64)
    if t.dtype.kind in "iu":
        return t.astype(np.int64) * int(scale)
    return np.rint(t.astype(np.float64) * scale).astype(np.int64)


#: fewer distinct times than this, for at least :data:`_COLLAPSE_EVENTS` events, means the
#: times were read in the wrong unit (a DAVIS records thousands of distinct µs per frame)
_COLLAPSE_DISTINCT = 16
_COLLAPSE_EVENTS = 1000


def collapsed_times(t_us: np.ndarray, unit: str) -> str | None:
    """A warning when many events share a handful of times — what seconds read as
    microseconds (or a unit too coarse) look like — else None. ``t_us``: int64 µs."""
    if len(t_us) < _COLLAPSE_EVENTS:
        return None
    distinct = len(np.unique(t_us))
    if distinct >= _COLLAPSE_DISTINCT:
        return None
    span = int(t_us.max() - t_us.min())
    return (f"{len(t_us)} events fall on only {distinct} distinct times ({span} µs in all, read "
            f"as {unit}): the time unit is probably wrong — set `time_unit`")
