"""What every reader returns: a :class:`Recording` — sensor size, events by time window, and
(optionally) frames with exposure windows. Readers never transform; transforms never open files.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..events import EventStream, Exposure

__all__ = ["Frame", "Recording", "MemoryRecording", "ReadOptions"]


@dataclass(frozen=True)
class ReadOptions:
    """How to interpret a file whose format leaves things open.

    Attributes:
        columns: order of the text columns, e.g. ``("t", "y", "x", "p")``; None = ``t x y p``.
        one_based: coordinates in the file count from 1.
        time_unit: ``"s" | "ms" | "us" | "ns"`` overriding the format's own rule (None = default:
            integer = µs, float = seconds).
        sensor: (width, height) for files that store no size.
        frame_size: (width, height) of the frames given with the events: the sensor's size
            when neither ``sensor`` nor the file states one (a frame's size is the sensor's;
            the largest event coordinate only bounds it).
        exposure_length_us: the exposure time of every frame, µs, for files whose frames carry
            one time stamp and no exposure (ROS bags without exposure messages, the RPG
            layout); None = unknown.
        stamp: what such a frame's stamp marks: ``"start"`` (None: the default) or
            ``"middle"`` of its exposure.
        topics: the ROS bag topics to read (events, images, exposure times); None = choose
            them from the message types.
    """

    columns: tuple[str, ...] | None = None
    one_based: bool = False
    time_unit: str | None = None
    sensor: tuple[int, int] | None = None
    frame_size: tuple[int, int] | None = None
    exposure_length_us: int | None = None
    stamp: str | None = None
    topics: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        from ..units import UNIT_SCALE_US

        for name in ("sensor", "frame_size"):
            size = getattr(self, name)
            if size is not None and not (
                    len(size) == 2 and all(isinstance(v, (int, np.integer))
                                           and not isinstance(v, bool) and 0 < v <= 65535
                                           for v in size)):
                raise InputError(f"`{name}` {size!r} is not (width, height) in whole pixels "
                                 "1..65535", hint="e.g. `sensor=(346, 260)`")
        if self.columns is not None and sorted(c for c in self.columns if c != "_") != \
                ["p", "t", "x", "y"]:
            raise InputError(f"`columns` {self.columns!r} must name t, x, y and p once each "
                             "(`_` for a column to skip)", hint="e.g. `columns=t,y,x,p`")
        if self.time_unit is not None and self.time_unit not in UNIT_SCALE_US:
            raise InputError(f"`time_unit` {self.time_unit!r} is not one of s, ms, us, ns",
                             hint="e.g. `time_unit='us'`")


@dataclass(frozen=True, eq=False)
class Frame:
    """One intensity frame.

    Attributes:
        image: float32 in [0, 1], (H, W) gray or (H, W, 3) RGB; linear as stored.
        exposure: the exposure window in µs on the events' clock, or None if unknown.
        index: frame number (from the file name or position).
        name: where it came from, for messages and output folder names.
        note: a warning about the frame as read (values outside [0, 1] clipped), or None.
    """

    image: np.ndarray
    exposure: Exposure | None
    index: int
    name: str
    note: str | None = None


class Recording(ABC):
    """An opened event file. Subclasses that can, read windows lazily (bounded memory)."""

    path: Path
    format: str
    width: int
    height: int
    #: warnings collected while opening (size guessed, etc.), printed by the CLI
    warnings: list[str]
    #: how to give the frames' exposure times when the file stores frames without them (None:
    #: the generic advice); readers of frames with one time stamp set it
    exposure_hint: str | None = None
    #: the unit the file's own times were read in where the file decides it (float seconds,
    #: integer µs, or `time_unit` as given): a window given without a unit is read in it;
    #: None where the format fixes its clock (camera formats)
    times_unit: str | None = None

    @abstractmethod
    def events(self, start_us: float | None = None, end_us: float | None = None) -> EventStream:
        """Events with ``start_us <= t < end_us`` (None = open end)."""

    @abstractmethod
    def num_events(self) -> int: ...

    def is_empty(self) -> bool:
        """Whether the recording holds no event (cheaper than counting them for some)."""
        return self.num_events() == 0

    @abstractmethod
    def time_range_us(self) -> tuple[int, int]:
        """(first, last) event time in µs; (0, 0) when there are no events."""

    def iter_chunks(self, max_events: int = 1 << 22) -> Iterator[EventStream]:
        """All events in time order, in pieces of at most ``max_events`` where the format
        allows (bounded memory for whole-file statistics and conversion)."""
        yield self.events()

    def iter_events(self, start_us: float | None = None, end_us: float | None = None,
                    max_events: int = 1 << 22) -> Iterator[EventStream]:
        """The events of ``[start_us, end_us)`` in time order, in pieces of at most
        ``max_events`` where the format allows (memory: one piece, however long the span)."""
        ev = self.events(start_us, end_us)
        step = max(int(max_events), 1)
        for i in range(0, len(ev), step):
            yield ev.take(slice(i, i + step))

    def iter_windows(self, exposures: Sequence[Exposure],
                     margin_us: int = 0) -> Iterator[EventStream]:
        """Events with ``start - margin <= t <= end + margin`` per window, in the given order.
        Chunked readers override this with one pass over the file (memory: one window)."""
        for e in exposures:
            yield self.events(e.start_us - margin_us, e.end_us + margin_us + 1)

    def frames(self) -> Iterator[Frame]:
        """Frames stored in the file, in time order (none by default)."""
        return iter(())

    def frame_exposures(self) -> list[Exposure]:
        """Exposure windows of the stored frames (cheap: no pixel data)."""
        return [f.exposure for f in self.frames() if f.exposure is not None]

    def stored_windows(self) -> list[Exposure]:
        """Exposure windows stored without frames (npz ``exposure_start``/``exposure_end``)."""
        return []

    def sensor_size(self) -> tuple[int, int]:
        return (self.width, self.height)

    def close(self) -> None:  # noqa: B027 - optional hook, most readers hold nothing open
        pass

    def __enter__(self) -> "Recording":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass(eq=False)
class MemoryRecording(Recording):
    """A recording whose events are held in memory (text, npz, mat, small files)."""

    stream: EventStream
    path: Path
    format: str
    frame_list: Sequence[Frame] = ()
    windows: Sequence[Exposure] = ()
    warnings: list[str] = field(default_factory=list)
    times_unit: str | None = None

    @property
    def width(self) -> int:  # type: ignore[override]
        return self.stream.width

    @property
    def height(self) -> int:  # type: ignore[override]
        return self.stream.height

    def events(self, start_us=None, end_us=None) -> EventStream:
        lo = -np.inf if start_us is None else start_us
        hi = np.inf if end_us is None else end_us
        return self.stream.slice(lo, hi)

    def num_events(self) -> int:
        return len(self.stream)

    def time_range_us(self) -> tuple[int, int]:
        return self.stream.time_range_us

    def frames(self) -> Iterator[Frame]:
        return iter(self.frame_list)

    def stored_windows(self) -> list[Exposure]:
        return list(self.windows)
