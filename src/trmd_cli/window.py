"""Exposure windows: which time span of the events belongs to each blurry frame.

One pure function, :func:`resolve_windows`, decides it for every command (deblur, hfr, voxelize),
first rule that applies:

1. ``exposure=(T0, T1)`` given by the user, in ``time_unit``; else numbers with a fraction are
   seconds and whole numbers are in the unit the file's own times were read in
   (:attr:`~trmd_cli.read.base.Recording.times_unit`: a file of float seconds, seconds), else
   µs (:func:`exposure_from_user`);
2. the exposure windows of frames stored in the recording;
3. windows stored without frames (npz ``exposure_start`` / ``exposure_end``);
4. the span of all events, with a warning.

A window that lies entirely outside the events' time range is an :class:`InputError`. A window
inside the recording that simply holds no events is *not* an error: whoever reads the events of
that window (``deblur.py``) warns and passes the frame through.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from .errors import InputError
from .events import Exposure
from .units import UNIT_SCALE_US

__all__ = ["WindowPlan", "resolve_windows", "exposure_from_user", "check_in_range",
           "check_windows"]


class WindowPlan(NamedTuple):
    """Result of :func:`resolve_windows`.

    Attributes:
        windows: exposure windows in µs on the events' clock (time offset applied), in order.
        warnings: human-readable warnings for the CLI to print (library code never prints).
        source: ``"option" | "frames" | "stored" | "span"`` — which rule applied.
    """

    windows: list[Exposure]
    warnings: list[str]
    source: str


def exposure_from_user(t0: float, t1: float, time_unit: str | None = None,
                       file_unit: str | None = None) -> Exposure:
    """``exposure=(T0, T1)`` → :class:`Exposure` in µs.

    ``time_unit`` is the unit the user set. When None, the values follow the same rule as
    files: numbers with a fraction are seconds; whole numbers are in ``file_unit``, the unit
    the file's own times were read in (a file of float seconds: seconds), else µs. A value
    that is not a whole number of µs is refused (event times are whole µs: it would be
    rounded).
    """
    for v in (t0, t1):
        if not np.isfinite(v):
            raise InputError(f"`exposure` value {v} is not a finite number")
    if time_unit is None:
        whole = float(t0).is_integer() and float(t1).is_integer()
        time_unit = (file_unit or "us") if whole else "s"
    unit = time_unit.replace("µs", "us")
    if unit not in UNIT_SCALE_US:
        raise InputError(f"unknown time unit {time_unit!r}", hint="use s, ms, us or ns")
    scale = UNIT_SCALE_US[unit]
    for v in (t0, t1):
        us = float(v) * scale
        # as for the file's times (:func:`~trmd_cli.units.to_microseconds`): beyond ±2**62 µs
        # (≈146 000 years) a value is a unit mistake, and int64 time overflows
        if abs(us) >= 2.0**62:
            raise InputError(f"`exposure` value {v:g} {unit} is out of range",
                             hint="give T0 T1 in µs (whole numbers) or s, or set `time_unit`")
        if abs(us - round(us)) > max(1e-3, 4 * float(np.spacing(abs(us)))):
            # event times are whole µs: a window between them would be rounded, silently
            raise InputError(f"`exposure` value {v:g} {unit} is {us:g} µs, not a whole number "
                             "of microseconds",
                             hint="give T0 T1 in whole µs, or set `time_unit`")
    start, end = (int(round(float(v) * scale)) for v in (t0, t1))
    if end <= start:
        raise InputError(f"`exposure=({t0}, {t1})` is empty or reversed "
                         f"({start}..{end} µs after `time_unit` {unit})",
                         hint="give T1 > T0 (whole numbers are µs, others s, unless `time_unit` "
                         "is set)")
    return Exposure(start, end)


def check_in_range(window: Exposure, time_range_us: tuple[int, int], what: str = "window",
                   path=None) -> None:
    """Raise :class:`InputError` if ``window`` does not overlap ``[first, last]`` event time."""
    first, last = time_range_us
    if window.end_us < first or window.start_us > last:
        raise InputError(
            f"the {what} [{window.start_us}, {window.end_us}] µs lies outside the events' time "
            f"range [{first}, {last}] µs ({first / 1e6:.6f}–{last / 1e6:.6f} s)", path=path,
            hint="check `exposure`, `time_unit` and `offset_us`")


def check_windows(windows: Sequence[Exposure], recording, path=None) -> None:
    """Bad input if the recording holds no events, or *every* window misses them (a few may:
    they pass through)."""
    if not windows:
        return
    if recording.is_empty():
        # else the line would blame the windows, against a time range of [0, 0]
        raise InputError("the recording holds no events", path=path,
                         hint="check the file (trmd info)")
    trange = recording.time_range_us()
    first, last = trange
    if all(w.end_us < first or w.start_us > last for w in windows):
        check_in_range(windows[0], trange, "exposure window", path)


def resolve_windows(
    recording,
    exposure: Sequence[float] | Exposure | None = None,
    time_unit: str | None = None,
    *,
    offset_us: int = 0,
) -> WindowPlan:
    """Decide the exposure window(s) for a recording (see the module docstring for the rules).

    Args:
        recording: a :class:`~trmd_cli.read.base.Recording` (only ``time_range_us``,
            ``frame_exposures``, ``stored_windows``, ``num_events`` and ``path`` are used).
        exposure: ``(T0, T1)`` in ``time_unit`` (None: see :func:`exposure_from_user`, with
            the recording's ``times_unit``), or an :class:`Exposure` already in µs.
        time_unit: the file's time unit for ``exposure``; see
            :func:`exposure_from_user`.
        offset_us: added to every window: moves the exposure relative to
            the events (real DAVIS data often needs tens of ms).

    Returns:
        :class:`WindowPlan` ``(windows, warnings, source)``; ``windows`` has one entry per stored
        frame when rule 2 applies (frames without an exposure are skipped with a warning).

    Raises:
        InputError: the recording has no events; an explicit window lies outside the events'
            time range; every stored window lies outside it.
    """
    path = getattr(recording, "path", None)
    if recording.is_empty():
        raise InputError("the recording holds no events", path=path,
                         hint="check the file (trmd info)")
    trange = recording.time_range_us()
    warnings: list[str] = []

    if exposure is not None:
        win = exposure if isinstance(exposure, Exposure) else exposure_from_user(
            float(exposure[0]), float(exposure[1]), time_unit, recording.times_unit)
        win = win.shifted(offset_us) if offset_us else win
        check_in_range(win, trange, "exposure window", path)
        _warn_partial([win], trange, warnings)
        return WindowPlan([win], warnings, "option")

    source = "frames"
    windows = list(recording.frame_exposures())
    if not windows:
        source = "stored"
        windows = list(recording.stored_windows())
    if not windows:
        first, last = trange
        win = Exposure(first, max(last, first + 1))
        warnings.append(
            f"no exposure window given or stored; using the events' whole span "
            f"[{win.start_us}, {win.end_us}] µs — pass `exposure=(T0, T1)` to choose one")
        return WindowPlan([win.shifted(offset_us) if offset_us else win], warnings, "span")

    if offset_us:
        windows = [w.shifted(offset_us) for w in windows]
    first, last = trange
    outside = [i for i, w in enumerate(windows) if w.end_us < first or w.start_us > last]
    if len(outside) == len(windows):
        check_in_range(windows[0], trange, f"{source} exposure window", path)
    if outside:
        warnings.append(
            f"{len(outside)} of {len(windows)} exposure windows lie outside the events' time "
            f"range (first: #{outside[0]}): they hold no events (deblur passes their frames "
            "through unchanged; their voxels are zero)")
    skip = set(outside)
    _warn_partial([w for i, w in enumerate(windows) if i not in skip], trange, warnings)
    return WindowPlan(windows, warnings, source)


def _warn_partial(windows: list[Exposure], trange: tuple[int, int], warnings: list[str]) -> None:
    first, last = trange
    # 5 % slack: the first/last event rarely sits exactly on a window's edge
    partial = [w for w in windows
               if max(first - w.start_us, w.end_us - last) > 0.05 * w.duration_us
               and not (w.end_us < first or w.start_us > last)]
    if partial:
        w = partial[0]
        warnings.append(
            f"{len(partial)} exposure window(s) extend beyond the events' time range "
            f"[{first}, {last}] µs (e.g. [{w.start_us}, {w.end_us}]); "
            "events are missing for part of the exposure")
