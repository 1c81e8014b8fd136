"""The one typed form of an event stream, and of an exposure window.

Units are fixed here for the whole library: time in integer microseconds (int64), coordinates as
uint16 column ``x`` / row ``y`` (row 0 = top), polarity int8 ±1. Readers convert on the way in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError

__all__ = ["EventStream", "Exposure", "EVENT_DTYPE", "US_PER_S"]

US_PER_S = 1_000_000
#: |time| bound in µs (≈146 000 years): beyond it a value is a unit mistake, and int64 overflows
_T_LIMIT_US = 2.0**62

#: Structured dtype used when events travel as one array (npz/npy structured files, writers).
EVENT_DTYPE = np.dtype([("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])


@dataclass(frozen=True)
class Exposure:
    """An exposure window ``[start_us, end_us]`` in integer microseconds."""

    start_us: int
    end_us: int

    def __post_init__(self) -> None:
        if not self.end_us > self.start_us:
            raise InputError(
                f"exposure window [{self.start_us}, {self.end_us}] µs is empty or reversed",
                hint="give `exposure=(T0, T1)` with T1 > T0",
            )

    @property
    def duration_us(self) -> int:
        return self.end_us - self.start_us

    @property
    def mid_us(self) -> float:
        return 0.5 * (self.start_us + self.end_us)

    def instants_us(self, n: int) -> np.ndarray:
        """The 2N+1 latent-frame instants t0 + k·T/(2N), k = 0..2N, as float64 µs."""
        n = check_n(n)
        return self.start_us + np.arange(2 * n + 1) * (self.duration_us / (2 * n))

    def shifted(self, offset_us: int) -> "Exposure":
        return Exposure(self.start_us + offset_us, self.end_us + offset_us)


def check_n(n, name: str = "N", hint: str = "use `n=3` (7 latent frames)") -> int:
    """``n`` as an int, refused unless a whole number ≥ 1 (N, or another count ``name``)."""
    if isinstance(n, bool) or not isinstance(n, (int, float, np.integer, np.floating)) \
            or int(n) != n or n < 1:
        raise InputError(f"{name} must be a whole number ≥ 1, got {n!r}", hint=hint)
    return int(n)


@dataclass(frozen=True, eq=False)
class EventStream:
    """Events sorted by time, immutable: the arrays are held as read-only views (what is
    derived from a stream, e.g. a window's EDI model, is kept for it by identity).

    Attributes:
        x: (E,) uint16 column, 0..width-1.
        y: (E,) uint16 row, 0..height-1 (0 = top).
        t: (E,) int64 microseconds, non-decreasing.
        p: (E,) int8, +1 (ON) or -1 (OFF).
        width, height: sensor size in pixels.
    """

    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    p: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("x", "y", "t", "p"):
            arr = getattr(self, name)
            if isinstance(arr, np.ndarray) and arr.flags.writeable:
                view = arr.view()  # (the caller's own array keeps its flags)
                view.setflags(write=False)
                object.__setattr__(self, name, view)
        n = len(self.t)
        for name in ("x", "y", "p"):
            if len(getattr(self, name)) != n:
                raise InputError(f"event arrays differ in length: t has {n}, {name} has "
                                 f"{len(getattr(self, name))}",
                                 hint="x, y, t and p need one entry per event")
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"sensor size {self.width}x{self.height} is not positive",
                             hint="pass `sensor=(W, H)`")

    def __len__(self) -> int:
        return len(self.t)

    @property
    def sensor_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return (self.width, self.height)

    @property
    def time_range_us(self) -> tuple[int, int]:
        if len(self.t) == 0:
            return (0, 0)
        return int(self.t[0]), int(self.t[-1])

    def slice(self, start_us: float, end_us: float) -> "EventStream":
        """Events with ``start_us <= t < end_us`` as views (binary search, no copy)."""
        i0, i1 = np.searchsorted(self.t, [start_us, end_us], side="left")
        return self.take(slice(int(i0), int(i1)))

    def within(self, exposure: Exposure) -> "EventStream":
        """Events of an exposure window, ``start_us <= t <= end_us`` (its end instant belongs
        to it), as views."""
        i0 = int(np.searchsorted(self.t, exposure.start_us, side="left"))
        i1 = int(np.searchsorted(self.t, exposure.end_us, side="right"))
        return self.take(slice(i0, i1))

    def take(self, index) -> "EventStream":
        return EventStream(self.x[index], self.y[index], self.t[index], self.p[index],
                           self.width, self.height)

    @classmethod
    def empty(cls, width: int, height: int) -> "EventStream":
        return cls(np.zeros(0, np.uint16), np.zeros(0, np.uint16), np.zeros(0, np.int64),
                   np.zeros(0, np.int8), width, height)

    @classmethod
    def concatenate(cls, parts: list["EventStream"]) -> "EventStream":
        """One stream of the events of ``parts`` (of one sensor), in time order: parts that
        overlap in time are merged (a stable sort: events of equal time keep the parts'
        order)."""
        if not parts:
            raise InputError("no event streams to concatenate")
        w, h = parts[0].width, parts[0].height
        for k, b in enumerate(parts[1:], 1):
            if (b.width, b.height) != (w, h):
                raise InputError(f"part {k} is of a {b.width}x{b.height} sensor, part 0 of "
                                 f"{w}x{h}", hint="concatenate the events of one sensor")
        out = cls(*(np.concatenate([getattr(s, k) for s in parts]) for k in "xytp"), w, h)
        filled = [s for s in parts if len(s)]
        if any(b.t[0] < a.t[-1] for a, b in zip(filled, filled[1:])):  # noqa: B905
            out = out.take(np.argsort(out.t, kind="stable"))
        return out

    def to_structured(self) -> np.ndarray:
        out = np.empty(len(self), EVENT_DTYPE)
        out["t"], out["x"], out["y"], out["p"] = self.t, self.x, self.y, self.p
        return out


def make_stream(
    x,
    y,
    t_us,
    p,
    width: int | None = None,
    height: int | None = None,
    *,
    source: str | None = None,
    sort: bool = False,
    first: int = 0,
) -> EventStream:
    """Validate raw columns and build an :class:`EventStream` (never mutates the inputs).

    ``t_us`` must already be in microseconds (float is rounded). ``p`` may be {0,1}, {-1,1} or
    bool; 0 means OFF. When ``width``/``height`` are None they are taken as max+1 (the caller
    warns). Unsorted times raise unless ``sort`` is true. ``first``: the file's index of the
    first of these events (messages name events by their place in the file).

    Raises:
        InputError: NaN/infinite/negative times, unsorted times, coordinates outside the sensor,
            polarities other than {0, 1, -1}.
    """
    t = np.asarray(t_us)
    x = np.asarray(x)
    y = np.asarray(y)
    p = np.asarray(p)
    for name, arr in (("t", t), ("x", x), ("y", y), ("p", p)):
        if arr.ndim != 1:
            raise InputError(f"'{name}' has shape {arr.shape}, expected one value per event "
                             "(1-D)", path=source, hint="give each of x, y, t, p as a 1-D array")
    if not len(x) == len(y) == len(t) == len(p):
        raise InputError(f"event arrays differ in length: t has {len(t)}, x {len(x)}, y "
                         f"{len(y)}, p {len(p)}", path=source,
                         hint="x, y, t and p need one entry per event")
    if t.dtype.kind == "f":
        if len(t) and not np.isfinite(t).all():
            bad = int(np.flatnonzero(~np.isfinite(t))[0])
            raise InputError(f"event {first + bad} has a non-finite time ({t[bad]})", path=source,
                             hint="remove or repair the broken rows")
        if len(t) and np.abs(t).max() >= _T_LIMIT_US:
            raise InputError(f"event times up to {np.abs(t).max():g} µs are out of range",
                             path=source, hint="check `time_unit`")
        t = np.rint(t).astype(np.int64)
    elif t.dtype.kind in "iu":
        t = t.astype(np.int64, copy=False)
    else:
        raise InputError(f"event times have type {t.dtype}, expected numbers", path=source,
                         hint="store times as integer microseconds or float seconds")
    if len(t) and t.min() < 0:
        bad = int(np.argmin(t))
        raise InputError(f"event {first + bad} has a negative time ({t[bad]} µs)", path=source,
                         hint="times must count from the start of the recording; check `time_unit`")
    if len(t) > 1 and (np.diff(t) < 0).any():
        if not sort:
            bad = int(np.flatnonzero(np.diff(t) < 0)[0]) + 1
            raise InputError(f"event times are not sorted (event {first + bad} goes back in "
                             "time)",
                             path=source, hint="sort the events by time first")
        order = np.argsort(t, kind="stable")
        t, x, y, p = t[order], x[order], y[order], p[order]
    for name, arr in (("x", x), ("y", y)):
        if arr.dtype.kind == "f":
            if len(arr) and (not np.isfinite(arr).all() or (arr != np.round(arr)).any()):
                raise InputError(f"{name} coordinates are not whole numbers", path=source,
                                 hint="check the column order (`columns`)")
        elif arr.dtype.kind not in "iub":
            raise InputError(f"{name} coordinates have type {arr.dtype}", path=source,
                             hint="store x and y as integer pixel indices")
        if len(arr) and arr.min() < 0:
            raise InputError(f"{name} coordinate {int(arr.min())} is negative", path=source,
                             hint="if the file counts pixels from 1, pass `one_based=True`")
    for name, size in (("width", width), ("height", height)):
        # a size read from a file may be anything: check it before comparing coordinates to it
        if size is not None and (not np.isscalar(size) or not float(size).is_integer()
                                 or not 0 < size <= 65535):
            raise InputError(f"sensor {name} {size!r} is not a whole number in 1..65535",
                             path=source, hint="pass `sensor=(W, H)`")
    if width is None:
        width = int(x.max()) + 1 if len(x) else 1
    if height is None:
        height = int(y.max()) + 1 if len(y) else 1
    if len(x) and int(x.max()) >= width:
        raise InputError(f"x coordinate {int(x.max())} is outside the sensor width {width}",
                         path=source, hint="check `sensor=(W, H)` or the column order (`columns`)")
    if len(y) and int(y.max()) >= height:
        raise InputError(f"y coordinate {int(y.max())} is outside the sensor height {height}",
                         path=source, hint="check `sensor=(W, H)` or the column order (`columns`)")
    if width > 65535 or height > 65535:
        raise InputError(f"sensor size {width}x{height} is too large (coordinates up to "
                         f"{width - 1}, {height - 1})", path=source,
                         hint="check the column order (`columns`) and `sensor=(W, H)`")
    if p.dtype == bool:
        p8 = np.where(p, 1, -1).astype(np.int8)
    else:
        if p.dtype.kind not in "iuf":
            raise InputError(f"polarity has type {p.dtype}, expected numbers", path=source,
                             hint="store polarity as 0/1 or -1/+1")
        if len(p) and p.dtype.kind == "f" and not np.isfinite(p).all():
            raise InputError("polarity has non-finite values", path=source,
                             hint="remove or repair the broken rows")
        pi = p  # compared as stored: casting first would turn 1.5 into 1
        # three comparisons, not np.unique: that sorts, and costs more than reading the file
        if len(pi) and ((pi != 1) & (pi != 0) & (pi != -1)).any():
            seen = np.unique(pi)[:5].tolist()
            raise InputError(f"polarity values {seen} are not in {{0, 1, -1}}",
                             path=source, hint="check the column order (`columns`)")
        # 2·(p > 0) − 1 in int8 in place: np.where's int64 temporary cost 6× more
        p8 = np.greater(pi, 0).view(np.int8)
        p8 = np.multiply(p8, 2, dtype=np.int8)
        np.subtract(p8, 1, out=p8)
    return EventStream(x.astype(np.uint16), y.astype(np.uint16), t, p8, int(width), int(height))
