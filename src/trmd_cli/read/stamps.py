"""Frames known by one time stamp, and clocks finer than a microsecond.

ROS bags and the RPG text layout give each frame a single time stamp, not an exposure window,
and count time in nanoseconds. Two rules, shared by both readers:

* **Exposure windows.** A frame's window is ``[s, s + L]`` µs (``stamp="start"``, the default)
  or ``[s - ⌊L/2⌋, s - ⌊L/2⌋ + L]`` (``stamp="middle"``), where ``s`` is its stamp and ``L`` its
  exposure time: the one the file stores, else ``exposure_length_us``. libcaer (and so
  rpg_dvs_ros) stamps a frame at ``start + ⌊L/2⌋`` in whole µs, so ``"middle"`` recovers its
  window exactly, even for an odd ``L``.
* **Nanoseconds → microseconds.** Times keep their whole microseconds; the sub-µs remainder is
  dropped (floor: ``t_us = t_ns // 1000``). DAVIS drivers stamp every event and frame as one
  nanosecond start instant plus whole device µs, so every time of a recording shares one
  remainder: flooring then moves all of them by the same amount (< 1 µs) and keeps every
  interval exact. When the remainders differ, intervals can change by < 1 µs;
  :class:`SubMicrosecond` notices it and says so once.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..errors import FormatError, InputError
from ..events import Exposure

__all__ = ["STAMPS", "ns_to_us", "SubMicrosecond", "stamped_exposures", "check_stamp",
           "pixels_to_float", "EXPOSURE_HINT"]

#: what a frame's stamp can mark
STAMPS = ("start", "middle")

#: hint for frames whose exposure time is unknown (`exposure_length_us` → --exposure-length)
EXPOSURE_HINT = ("pass `exposure_length_us` (the exposure time of every frame, e.g. 20ms), and "
                 "`stamp='middle'` if the stamps mark the middle of the exposure")


def check_stamp(stamp: str | None) -> str:
    """``None`` → ``"start"``; anything but ``start`` / ``middle`` is bad input."""
    if stamp is None:
        return "start"
    if stamp not in STAMPS:
        raise InputError(f"`stamp={stamp!r}` is neither 'start' nor 'middle'",
                         hint="pass `stamp='start'` (the default) or `stamp='middle'`")
    return stamp


def ns_to_us(t_ns: np.ndarray) -> np.ndarray:
    """int64 nanoseconds → int64 whole microseconds, the remainder dropped (floor)."""
    return np.floor_divide(np.asarray(t_ns, np.int64), 1000)


class SubMicrosecond:
    """Watches the sub-µs remainders of the nanosecond times of one recording.

    Call :meth:`add` with every array of nanosecond times (events and frame stamps alike); then
    :meth:`note` is a warning when the remainders differ — when flooring to µs may have changed
    an interval by up to 1 µs — else None.
    """

    def __init__(self) -> None:
        self._first: int | None = None
        self.mixed = False

    def add(self, t_ns: np.ndarray) -> None:
        if self.mixed or len(t_ns) == 0:
            return
        rem = np.remainder(np.asarray(t_ns, np.int64), 1000)
        if self._first is None:
            self._first = int(rem[0])
        if (rem != self._first).any():
            self.mixed = True

    def note(self) -> str | None:
        if not self.mixed:
            return None
        return ("the file's times are finer than a microsecond and do not share one sub-µs "
                "remainder: trmd keeps whole microseconds (the remainder dropped), so intervals "
                "may differ from the file's by less than 1 µs")


def stamped_exposures(stamps_us: Sequence[int], lengths_us: Sequence[int | None] | None,
                      exposure_length_us: int | None, stamp: str | None,
                      stored: str = "the file") -> tuple[list[Exposure | None], list[str]]:
    """The exposure window of every stamped frame (see the module docstring for the rule).

    Args:
        stamps_us: each frame's time stamp, µs.
        lengths_us: each frame's exposure time stored in the file, µs (None where it stores
            none), or None when the file stores none at all.
        exposure_length_us: the user's exposure time for frames without a stored one, µs.
        stamp: ``"start"`` / ``"middle"`` (None = ``"start"``).
        stored: how messages name where stored exposure times come from.

    Returns:
        (windows, warnings): a window per frame, None where no exposure time is known.
    Raises:
        InputError: ``exposure_length_us`` not positive, or ``stamp`` unknown.
    """
    where = check_stamp(stamp)
    if exposure_length_us is not None and not int(exposure_length_us) > 0:
        raise InputError(f"`exposure_length_us={exposure_length_us}` is not a positive "
                         "duration", hint="pass the exposure time of every frame, e.g. 20ms")
    warnings: list[str] = []
    n = len(stamps_us)
    if lengths_us is not None and exposure_length_us is not None and any(
            v is not None for v in lengths_us):
        warnings.append(f"`exposure_length_us` ignored: {stored} stores each frame's exposure "
                        "time")
    lengths: list[int | None] = [None] * n
    if lengths_us is not None:
        lengths = [None if v is None or int(v) <= 0 else int(v) for v in lengths_us]
        bad = sum(v is not None and int(v) <= 0 for v in lengths_us)
        if bad:
            warnings.append(f"{bad} of {n} frames have an exposure time ≤ 0 in {stored}; they "
                            "cannot be deblurred")
        if all(v is None for v in lengths_us) and exposure_length_us is not None:
            lengths = [int(exposure_length_us)] * n
    elif exposure_length_us is not None:
        lengths = [int(exposure_length_us)] * n
    out: list[Exposure | None] = []
    for s, length in zip(stamps_us, lengths, strict=True):
        if length is None:
            out.append(None)
            continue
        start = int(s) if where == "start" else int(s) - length // 2
        out.append(Exposure(start, start + length))
    missing = sum(w is None for w in out)
    if n and missing == n and lengths_us is None:
        warnings.append(f"the {n} frames carry a time stamp but no exposure time: to deblur "
                        f"them, {EXPOSURE_HINT}")
    return out, warnings


def pixels_to_float(pixels: np.ndarray, order: str = "gray", *, max_value: int | None = None,
                    path=None) -> np.ndarray:
    """Raw pixels → float32 [0, 1]: (H, W) gray or (H, W, 3) RGB.

    ``order``: ``gray``, ``rgb``, ``bgr``, ``rgba`` or ``bgra`` (alpha dropped). ``max_value``:
    full scale (default: 255 for 8-bit, 65535 for 16-bit). Colour whose three channels are equal
    comes back gray, as images read from disk do.
    """
    px = np.asarray(pixels)
    if px.dtype.kind not in "ui":
        raise FormatError(f"unsupported pixel type {px.dtype}", path=path)
    scale = float(max_value if max_value is not None else
                  (65535 if px.dtype.itemsize > 1 else 255))
    img = px.astype(np.float32) / scale
    if order != "gray":
        img = img[..., :3]
        if order.startswith("bgr"):
            img = img[..., ::-1]
        if np.array_equal(img[..., 0], img[..., 1]) and np.array_equal(img[..., 1],
                                                                         img[..., 2]):
            img = img[..., 0]
    return np.ascontiguousarray(np.clip(img, 0.0, 1.0))
