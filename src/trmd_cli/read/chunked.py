"""Recordings decoded chunk by chunk: camera files too large to hold in memory.

A :class:`ChunkedRecording` makes one pass over the file when it is opened, checking every chunk
(times non-decreasing, coordinates inside the sensor) and keeping a small index — per chunk its
first and last time and its event count. Afterwards

* ``events(t0, t1)`` decodes only the chunks that overlap ``[t0, t1)``: formats that can seek
  jump straight to them, the others decode from the start and skip. The decoder stays open
  between calls, so windows requested in time order (one ``events`` call per frame) cost one
  pass over the file in total, holding one window plus one chunk; readers that set
  :attr:`ChunkedRecording.gathers` decode a span of many chunks straight into one set of arrays;
* ``iter_windows`` over windows whose starts do not go back sweeps the file once, the bounds of
  all the windows found in each chunk by one binary search (memory: one window and its chunks);
* files of at most :data:`CACHE_MAX_EVENTS` events are kept in memory after the first pass, so
  small recordings cost one decode whatever is asked of them.

A reader may index a chunk without decoding it (:class:`ChunkSummary`) when it can check the
chunk on its raw bytes for less than a decoding costs (.dat). A reader may also index bounds on
its chunks' times instead of the times (large EVT 3.0 files: every event of chunk k lies in
``[_first[k], _last[k]]``): it then builds the index itself and checks each chunk as it decodes
it (:meth:`ChunkedRecording._check_inside`); windows slice every chunk they touch.
"""

from __future__ import annotations

import math
from abc import abstractmethod
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError
from ..events import EventStream, Exposure
from .base import Recording

__all__ = ["Chunk", "ChunkSummary", "ChunkedRecording", "CACHE_MAX_EVENTS", "IN_ORDER_HINT",
           "time_slice"]

#: what a camera file whose times go back should do
IN_ORDER_HINT = "camera files are written in time order; re-export the recording"
#: recordings with at most this many events stay in memory after opening (~13 bytes per event)
CACHE_MAX_EVENTS = 10_000_000


def _left(t: np.ndarray, bound: float) -> int:
    if bound != bound:  # NaN: after every time, as numpy sorts it
        return len(t)
    if bound in (np.inf, -np.inf):
        return 0 if bound < 0 else len(t)
    # t holds integers: t >= bound exactly when t >= ceil(bound). An integer bound keeps the
    # search in int64 (a float one would have numpy convert all of t to float64 first)
    b = min(max(math.ceil(bound), -(1 << 63)), (1 << 63) - 1)
    return int(np.searchsorted(t, b, side="left"))


def time_slice(t: np.ndarray, lo: float, hi: float) -> slice:
    """The positions of ``lo <= t < hi`` in the sorted integer times ``t`` (µs)."""
    return slice(_left(t, lo), _left(t, hi))


@dataclass(frozen=True, eq=False)
class Chunk:
    """One decoded piece of a file, already in library units.

    Attributes:
        ordinal: position of the chunk in decode order (0, 1, …), empty chunks included.
        x, y: (E,) uint16 column / row. t: (E,) int64 µs. p: (E,) int8 ±1.
        resume: what the decoder needs to restart at this chunk (None: it cannot seek).
    """

    ordinal: int
    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    p: np.ndarray
    resume: Any = None


@dataclass(frozen=True)
class ChunkSummary:
    """What the index keeps of a chunk a reader checked without decoding it into events.

    The reader vouches that the chunk's times do not go back within it (the index still checks
    them against the chunks before); it is never kept in memory.

    Attributes:
        ordinal: as :attr:`Chunk.ordinal`. first_us, last_us: its first and last time, µs.
        count: its number of events (> 0). xmax, ymax: its largest column and row.
        resume: as :attr:`Chunk.resume`.
    """

    ordinal: int
    first_us: int
    last_us: int
    count: int
    xmax: int
    ymax: int
    resume: Any = None


class ChunkedRecording(Recording):
    """Base class: subclasses implement :meth:`_decode` and call :meth:`_build_index` once.

    ``width``/``height`` may be None before indexing (the file stores no size); the index pass
    then takes max+1 and records a warning.
    """

    def __init__(self, path: Path, fmt: str, width: int | None, height: int | None,
                 warnings: list[str] | None = None) -> None:
        self.path = Path(path)
        self.format = fmt
        self.width = width  # type: ignore[assignment]
        self.height = height  # type: ignore[assignment]
        self.warnings = [] if warnings is None else warnings
        self._cache: EventStream | None = None
        self._live: Iterator[Chunk] | None = None  # decoder kept open between requests
        self._live_next = 0  # ordinal of the next chunk it yields
        self._recent: list[Chunk] = []  # chunks of the last request, plus one read ahead

    @abstractmethod
    def _decode(self, start: int = 0, resume: Any = None) -> Iterator[Chunk]:
        """Chunks in file order, from the chunk numbered ``start`` (whose ``resume`` is given)."""

    # -- index ------------------------------------------------------------------------------

    def _build_index(self, chunks: Iterable[Chunk | ChunkSummary] | None = None,
                     cache_max: int | None = None) -> None:
        """One pass: validate every chunk, record its time span, keep small files in memory
        (only when every chunk came decoded: a :class:`ChunkSummary` holds no events)."""
        if cache_max is None:
            cache_max = CACHE_MAX_EVENTS
        ordinals: list[int] = []
        firsts: list[int] = []
        lasts: list[int] = []
        counts: list[int] = []
        resumes: list[Any] = []
        kept: list[Chunk] | None = []
        total = 0
        prev_last: int | None = None
        xmax = ymax = -1
        for ch in self._decode(0) if chunks is None else chunks:
            if isinstance(ch, ChunkSummary):
                if prev_last is not None and ch.first_us < prev_last:
                    raise self._time_error(total)
                xmax, ymax = max(xmax, ch.xmax), max(ymax, ch.ymax)
                ordinals.append(ch.ordinal)
                firsts.append(ch.first_us)
                lasts.append(ch.last_us)
                counts.append(ch.count)
                resumes.append(ch.resume)
                total += ch.count
                prev_last = ch.last_us
                kept = None
                continue
            n = len(ch.t)
            if n == 0:
                continue
            if n > 1 and bool(np.less(ch.t[1:], ch.t[:-1]).any()):
                back = np.flatnonzero(np.diff(ch.t) < 0)
                raise self._time_error(total + int(back[0]) + 1)
            if prev_last is not None and int(ch.t[0]) < prev_last:
                raise self._time_error(total)
            xmax = max(xmax, int(ch.x.max()))
            ymax = max(ymax, int(ch.y.max()))
            ordinals.append(ch.ordinal)
            firsts.append(int(ch.t[0]))
            lasts.append(int(ch.t[-1]))
            counts.append(n)
            resumes.append(ch.resume)
            total += n
            prev_last = lasts[-1]
            if kept is not None:
                kept.append(ch)
                if total > cache_max:
                    kept = None
        self._settle_size(xmax, ymax)
        self._ordinal = np.asarray(ordinals, np.int64)
        self._first = np.asarray(firsts, np.int64)
        self._last = np.asarray(lasts, np.int64)
        self._count = np.asarray(counts, np.int64)
        self._resume = resumes
        if kept is not None:
            self._cache = self._join(kept)

    def _time_error(self, index: int) -> FormatError:
        return FormatError(f"event {index} goes back in time (corrupt file?)", path=self.path,
                           hint=IN_ORDER_HINT)

    #: the warning when the file states no sensor size (``{w}``, ``{h}``: the size taken)
    size_guess_note = ("the file stores no sensor size; using {w}x{h} from the largest "
                       "coordinates (pass `sensor=(W, H)` to set it)")

    def _settle_size(self, xmax: int, ymax: int) -> None:
        if self.width is None or self.height is None:
            w, h = max(xmax + 1, 1), max(ymax + 1, 1)
            self.width = self.width or w  # type: ignore[assignment]
            self.height = self.height or h  # type: ignore[assignment]
            self.warnings.append(self.size_guess_note.format(w=self.width, h=self.height))
        self._check_inside(xmax, ymax)

    def _check_inside(self, xmax: int, ymax: int) -> None:
        """Bad input when the largest column or row lies outside the sensor."""
        if xmax >= self.width or ymax >= self.height:
            axis, value = ("x", xmax) if xmax >= self.width else ("y", ymax)
            raise FormatError(f"{axis} coordinate {value} is outside the {self.width}x"
                              f"{self.height} sensor (corrupt file, or wrong sensor size?)",
                              path=self.path, hint="check `sensor=(W, H)`")

    def _join(self, chunks: Sequence[Chunk]) -> EventStream:
        if not chunks:
            return EventStream.empty(self.width, self.height)
        if len(chunks) == 1:
            c = chunks[0]
            return EventStream(c.x, c.y, c.t, c.p, self.width, self.height)
        return EventStream(*(np.concatenate([getattr(c, k) for c in chunks]) for k in "xytp"),
                           self.width, self.height)

    def _window(self, chunks: Sequence[Chunk], lo: float, hi: float) -> EventStream:
        # slice each chunk before joining: a short window inside a big chunk copies little
        parts = [EventStream(c.x, c.y, c.t, c.p, self.width, self.height)
                 .take(time_slice(c.t, lo, hi)) for c in chunks]
        parts = [s for s in parts if len(s)]
        if not parts:
            return EventStream.empty(self.width, self.height)
        return parts[0] if len(parts) == 1 else EventStream.concatenate(parts)

    # -- Recording API ----------------------------------------------------------------------

    def num_events(self) -> int:
        return int(self._count.sum())

    def time_range_us(self) -> tuple[int, int]:
        if len(self._first) == 0:
            return (0, 0)
        return int(self._first[0]), int(self._last[-1])

    def events(self, start_us: float | None = None, end_us: float | None = None) -> EventStream:
        lo = -np.inf if start_us is None else start_us
        hi = np.inf if end_us is None else end_us
        if self._cache is not None:
            return self._cache.take(time_slice(self._cache.t, lo, hi))
        sel = np.flatnonzero((self._last >= lo) & (self._first < hi))
        if len(sel) == 0:
            return EventStream.empty(self.width, self.height)
        if self.gathers and len(sel) > 2:
            ev = self._gather(int(sel[0]), int(sel[-1]))
            return ev.take(time_slice(ev.t, lo, hi))
        return self._window(self._fetch(int(sel[0]), int(sel[-1])), lo, hi)

    #: spans of more than two chunks are decoded into one set of arrays (:meth:`_gather`)
    #: instead of joining chunks held together; readers whose chunks have the dtypes of
    #: :class:`Chunk` set it
    gathers = False

    def _gather(self, k0: int, k1: int) -> EventStream:
        """The events of the index's chunks k0..k1 in one set of arrays, each chunk copied in
        as it is decoded (memory: the result and one chunk, not the result twice)."""
        total = int(self._count[k0:k1 + 1].sum())
        x, y = np.empty(total, np.uint16), np.empty(total, np.uint16)
        t, p = np.empty(total, np.int64), np.empty(total, np.int8)
        w0, w1 = int(self._ordinal[k0]), int(self._ordinal[k1])
        at = 0
        source = self._decode(w0, self._resume[k0])
        try:
            for ch in source:
                if ch.ordinal < w0 or len(ch.t) == 0:
                    continue
                n = len(ch.t)
                if at + n > total:
                    break
                s = slice(at, at + n)
                x[s], y[s], t[s], p[s] = ch.x, ch.y, ch.t, ch.p
                at += n
                if ch.ordinal >= w1:
                    break
        finally:
            source.close()  # type: ignore[attr-defined]
        if at != total:
            raise FormatError(f"the file holds other events than when it was opened ({at:,} "
                              f"where {total:,} were counted)", path=self.path,
                              hint="read it again once nothing writes to it")
        return EventStream(x, y, t, p, self.width, self.height)

    def _fetch(self, k0: int, k1: int) -> list[Chunk]:
        """The chunks at index positions k0..k1, decoding as little as possible.

        The decoder of the previous request stays open, positioned after it, and the chunks it
        returned (plus one read ahead) are kept: requests that move forward through the file
        (one window after another) decode each chunk once in total, whether or not the format
        can seek. Memory: the chunks of one request plus one.
        """
        w0, w1 = int(self._ordinal[k0]), int(self._ordinal[k1])
        recent = self._recent
        if recent and recent[0].ordinal <= w0 <= recent[-1].ordinal:
            keep = [c for c in recent if c.ordinal >= w0]
            start = recent[-1].ordinal + 1
        else:
            keep, start = [], w0
        if start <= w1:
            seekable = self._resume[k0] is not None
            if self._live is None or self._live_next > start or (
                    seekable and not keep and self._live_next < start):
                # (re)start at the first wanted chunk: seekable formats jump straight there
                self._close_live()
                keep, start = [], w0
                self._live = self._decode(w0, self._resume[k0])
                self._live_next = w0
            while True:
                ch = next(self._live, None)
                if ch is None:
                    self._close_live()
                    break
                self._live_next = ch.ordinal + 1
                if ch.ordinal < start or len(ch.t) == 0:
                    continue
                keep.append(ch)
                if ch.ordinal > w1:
                    break
        self._recent = keep
        return [c for c in keep if c.ordinal <= w1]

    def _close_live(self) -> None:
        if self._live is not None:
            self._live.close()  # type: ignore[attr-defined]
        self._live = None
        self._live_next = 0

    def close(self) -> None:
        self._close_live()
        self._recent = []

    def iter_windows(self, exposures: Sequence[Exposure],
                     margin_us: int = 0) -> Iterator[EventStream]:
        """Events with ``start - margin <= t <= end + margin`` per window, in the given order.

        Windows whose starts do not go back are served by one sweep over the file: every chunk
        decoded once, the windows' bounds found in each chunk by one binary search for all of
        them, memory one window plus its chunks. Others take :meth:`events` one by one."""
        lo = np.array([e.start_us - margin_us for e in exposures])
        if self._cache is not None or len(lo) < 2 or np.any(lo[1:] < lo[:-1]):
            return super().iter_windows(exposures, margin_us)
        hi = np.array([e.end_us + margin_us + 1 for e in exposures])  # half-open
        return self._sweep(lo, hi)

    def _sweep(self, lo: np.ndarray, hi: np.ndarray) -> Iterator[EventStream]:
        # window i spans the index's chunks ka[i]..kb[i] (none when ka > kb): the chunks before
        # ka end before it starts, those after kb start after it ends
        ka = np.searchsorted(self._last, lo, side="left")
        kb = np.searchsorted(self._first, hi, side="left") - 1
        by_kb = np.argsort(kb, kind="stable")
        kb_sorted = kb[by_kb]
        start = np.zeros(len(lo), np.int64)  # window i's first event in chunk ka[i]
        stop = np.zeros(len(lo), np.int64)  # its end in chunk kb[i]
        held: dict[int, Chunk] = {}  # index position → decoded chunk
        source: Iterator[Chunk] | None = None
        source_next = 0  # ordinal of the next chunk the source yields

        def load(k: int) -> Chunk:
            nonlocal source, source_next
            want = int(self._ordinal[k])
            if source is None or source_next > want or (
                    self._resume[k] is not None and source_next < want):
                if source is not None:
                    source.close()  # type: ignore[attr-defined]
                source = self._decode(want, self._resume[k])
                source_next = want
            for ch in source:
                source_next = ch.ordinal + 1
                if ch.ordinal == want:
                    # the bounds of every window that starts or ends in this chunk, at once
                    a0, a1 = np.searchsorted(ka, [k, k + 1])
                    start[a0:a1] = np.searchsorted(ch.t, lo[a0:a1], side="left")
                    b0, b1 = np.searchsorted(kb_sorted, [k, k + 1])
                    ends = by_kb[b0:b1]
                    stop[ends] = np.searchsorted(ch.t, hi[ends], side="left")
                    return ch
            raise FormatError(f"chunk {want} was indexed but is not in the file any more",
                              path=self.path, hint="read it again once nothing writes to it")

        width, height = self.width, self.height
        low = 0  # the chunks held all are at or after it
        try:
            for i, (a, b) in enumerate(zip(ka.tolist(), kb.tolist(), strict=True)):
                if a > low:
                    for k in [k for k in held if k < a]:
                        del held[k]
                    low = a
                if a > b:
                    yield EventStream.empty(width, height)
                    continue
                for k in range(a, b + 1):
                    if k not in held:
                        held[k] = load(k)
                i0, i1 = int(start[i]), int(stop[i])
                if a == b:
                    c = held[a]
                    yield (EventStream(c.x[i0:i1], c.y[i0:i1], c.t[i0:i1], c.p[i0:i1], width,
                                       height) if i1 > i0 else EventStream.empty(width, height))
                    continue
                # every chunk sliced to the window: an index of time bounds (not the events'
                # own first and last times) lets the first run past it, a later one start
                # before it
                cuts = [(held[k], time_slice(held[k].t, lo[i], hi[i])) for k in range(a, b + 1)]
                cuts = [(c, s) for c, s in cuts if s.stop > s.start]
                if not cuts:
                    yield EventStream.empty(width, height)
                elif len(cuts) == 1:
                    c, s = cuts[0]
                    yield EventStream(c.x[s], c.y[s], c.t[s], c.p[s], width, height)
                else:  # the slices joined straight into the window's arrays
                    yield EventStream(*(np.concatenate([getattr(c, k)[s] for c, s in cuts])
                                        for k in "xytp"), width, height)
        finally:
            if source is not None:
                source.close()  # type: ignore[attr-defined]

    def iter_events(self, start_us: float | None = None, end_us: float | None = None,
                    max_events: int = 1 << 22) -> Iterator[EventStream]:
        """The events of ``[start_us, end_us)``, one decoded chunk at a time (sliced to at most
        ``max_events``): a span of the whole file costs one chunk of memory."""
        lo = -np.inf if start_us is None else start_us
        hi = np.inf if end_us is None else end_us
        step = max(int(max_events), 1)
        if self._cache is not None:
            ev = self._cache.take(time_slice(self._cache.t, lo, hi))
            for i in range(0, len(ev), step):
                yield ev.take(slice(i, i + step))
            return
        for k in np.flatnonzero((self._last >= lo) & (self._first < hi)):
            part = self._window(self._fetch(int(k), int(k)), lo, hi)
            for i in range(0, len(part), step):
                yield part.take(slice(i, i + step))

    def iter_chunks(self, max_events: int = 1 << 22) -> Iterator[EventStream]:
        """All events in time order, in pieces of at most ``max_events`` (one decoded chunk at a
        time in memory)."""
        step = max(int(max_events), 1)
        if self._cache is not None:
            for i in range(0, len(self._cache), step):
                yield self._cache.take(slice(i, i + step))
            return
        source = self._decode(0)
        try:
            for ch in source:
                for i in range(0, len(ch.t), step):
                    s = slice(i, i + step)
                    yield EventStream(ch.x[s], ch.y[s], ch.t[s], ch.p[s], self.width,
                                      self.height)
        finally:
            source.close()  # type: ignore[attr-defined]
