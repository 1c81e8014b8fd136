"""ROS 1 and ROS 2 bags of event cameras, read with the ``rosbags`` package (no ROS install).

What is read:

* events: one topic of ``dvs_msgs/EventArray`` (rpg_dvs_ros, its ROS 2 ports) or
  ``prophesee_event_msgs/EventArray`` (Prophesee's ROS drivers); both are ``Header header,
  uint32 height, uint32 width, Event[] events`` with ``Event`` = ``uint16 x, uint16 y, time
  ts, bool polarity``. The event arrays are decoded here with numpy straight from the
  serialized bytes (ROS 1: packed little-endian; ROS 2: CDR, either byte order), checked
  against ``rosbags``' own decoding on the first message;
* frames: one topic of ``sensor_msgs/Image`` (mono8/16, rgb8/bgr8/rgba8/bgra8, 8UC1/3/4,
  16UC1) or ``sensor_msgs/CompressedImage`` (PNG/JPEG), each frame stamped by its header;
* exposure times: a ``std_msgs/Int32`` (Int64, UInt32, UInt64) topic named ``…/exposure``, in
  µs, one message per image — what rpg_dvs_ros publishes as ``/dvs/exposure``.

Topics are chosen by message type when the bag holds one event topic and at most one image
topic (several image topics: the one in the event topic's namespace); ``topics`` names them
otherwise. Everything else (IMU, camera info …) is not read.

Units and conventions:

* time: ROS times (sec, nsec) → int64 ns → whole µs, the sub-µs remainder dropped (floor; see
  :mod:`trmd_cli.read.stamps`); event and frame times stay on the bag's clock (usually Unix
  time), nothing is subtracted;
* x = column, y = row, (0, 0) at the top-left; polarity True = +1, False = -1;
* sensor size: the event arrays' ``width`` × ``height``; if 0, ``sensor``, the first image's
  size, else max+1 (warned);
* a frame's exposure window: its stamp and its exposure time — the exposure topic's, else
  ``exposure_length_us`` — placed by ``stamp`` (``"start"`` by default, ``"middle"``), see
  :func:`~trmd_cli.read.stamps.stamped_exposures`. rpg_dvs_ros stamps the middle.

Memory: the bag is read message by message. Opening it makes one pass over the event messages
(validating them, indexing chunks of whole messages by bag time) and one over the image
headers; windows are then read by asking the bag for the messages from a chunk's bag time on
(:class:`~trmd_cli.read.chunked.ChunkedRecording`), frames decoded one at a time.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError, InputError
from ..events import Exposure
from .base import Frame, ReadOptions
from .chunked import Chunk, ChunkedRecording
from .stamps import EXPOSURE_HINT, SubMicrosecond, ns_to_us, pixels_to_float, stamped_exposures

__all__ = ["read_rosbag", "RosbagRecording", "MESSAGE_DEFINITIONS", "EVENT_TYPES",
           "IMAGE_TYPES", "EXPOSURE_TYPES", "decode_event_array", "ROS_CHUNK_EVENTS",
           "make_typestore"]

#: events gathered per chunk (whole messages)
ROS_CHUNK_EVENTS = 1 << 20

#: the event message definitions registered with rosbags (ROS 1 .msg syntax, as published)
MESSAGE_DEFINITIONS = {
    "dvs_msgs/msg/Event": "uint16 x\nuint16 y\ntime ts\nbool polarity\n",
    "dvs_msgs/msg/EventArray": "std_msgs/Header header\nuint32 height\nuint32 width\n"
                               "dvs_msgs/Event[] events\n",
    "prophesee_event_msgs/msg/Event": "uint16 x\nuint16 y\ntime ts\nbool polarity\n",
    "prophesee_event_msgs/msg/EventArray": "Header header\nuint32 height\nuint32 width\n"
                                           "prophesee_event_msgs/Event[] events\n",
}
EVENT_TYPES = ("dvs_msgs/msg/EventArray", "prophesee_event_msgs/msg/EventArray")
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
EXPOSURE_TYPES = ("std_msgs/msg/Int32", "std_msgs/msg/Int64", "std_msgs/msg/UInt32",
                  "std_msgs/msg/UInt64")

_DAMAGED = "the bag may be incomplete or damaged: copy it again"

#: one packed ROS 1 event: x, y, sec, nsec, polarity (13 bytes)
_EV1 = np.dtype({"names": ["x", "y", "sec", "nsec", "p"],
                 "formats": ["<u2", "<u2", "<u4", "<u4", "u1"],
                 "offsets": [0, 2, 4, 8, 12], "itemsize": 13})


def _cdr_events(order: str) -> tuple[np.dtype, np.dtype]:
    """CDR events: the first (aligned at 4: x, y, sec, nsec, polarity) and every later one (at
    2 mod 4: two padding bytes before sec), 16 bytes apart."""
    first = np.dtype({"names": ["x", "y", "sec", "nsec", "p"],
                      "formats": [order + "u2", order + "u2", order + "i4", order + "u4", "u1"],
                      "offsets": [0, 2, 4, 8, 12], "itemsize": 13})
    rest = np.dtype({"names": ["x", "y", "sec", "nsec", "p"],
                     "formats": [order + "u2", order + "u2", order + "i4", order + "u4", "u1"],
                     "offsets": [0, 2, 6, 10, 14], "itemsize": 15})
    return first, rest


_CDR = {"<": _cdr_events("<"), ">": _cdr_events(">")}


@dataclass(frozen=True, eq=False)
class EventArray:
    """One decoded event message: header stamp (ns), sensor size, events (t in ns)."""

    stamp_ns: int
    width: int
    height: int
    x: np.ndarray
    y: np.ndarray
    t_ns: np.ndarray
    p: np.ndarray


def decode_event_array(raw: bytes | memoryview, ros2: bool) -> EventArray:
    """A serialized ``dvs_msgs/EventArray`` / ``prophesee_event_msgs/EventArray`` → arrays.

    Raises:
        ValueError: the bytes do not hold such a message (wrong length, unknown encoding).
    """
    buf = memoryview(raw).cast("B")
    if not ros2:
        order, base, pos = "<", 0, 4  # uint32 seq
        sec = int.from_bytes(buf[pos:pos + 4], "little")
        nsec = int.from_bytes(buf[pos + 4:pos + 8], "little")
        pos += 8
    else:
        if len(buf) < 4 or buf[0] != 0 or buf[1] not in (0, 1):
            raise ValueError("not plain CDR (encapsulation kind "
                             f"{bytes(buf[:2]).hex() if len(buf) >= 2 else '?'})")
        order = "<" if buf[1] == 1 else ">"
        base, pos = 4, 4
        sec = int(np.frombuffer(buf, order + "i4", 1, pos)[0])
        nsec = int(np.frombuffer(buf, order + "u4", 1, pos + 4)[0])
        pos += 8
    endian = "little" if order == "<" else "big"
    n_str = int.from_bytes(buf[pos:pos + 4], endian)
    pos += 4 + n_str
    if ros2:
        pos += (-(pos - base)) % 4
    if pos + 12 > len(buf):
        raise ValueError("message shorter than its header")
    height = int.from_bytes(buf[pos:pos + 4], endian)
    width = int.from_bytes(buf[pos + 4:pos + 8], endian)
    n = int.from_bytes(buf[pos + 8:pos + 12], endian)
    o = pos + 12
    if not ros2:
        if len(buf) != o + 13 * n:
            raise ValueError(f"{n} events need {13 * n} bytes, the message has {len(buf) - o}")
        ev = np.frombuffer(buf, _EV1, n, o)
        x, y, s, ns, p = ev["x"], ev["y"], ev["sec"], ev["nsec"], ev["p"]
    else:
        need = 0 if n == 0 else (13 if n == 1 else 16 * n - 3)
        if not 0 <= len(buf) - o - need <= 3:  # CDR may pad the end to 4 bytes
            raise ValueError(f"{n} events need {need} bytes, the message has {len(buf) - o}")
        first, rest = _CDR[order]
        if n == 0:
            x = y = np.zeros(0, np.uint16)
            s = np.zeros(0, np.int64)
            ns = np.zeros(0, np.int64)
            p = np.zeros(0, np.uint8)
        else:
            e0 = np.frombuffer(buf, first, 1, o)
            er = np.ndarray((n - 1,), rest, buffer=buf, offset=o + 14, strides=(16,)) \
                if n > 1 else np.zeros(0, rest)
            x = np.concatenate([e0["x"], er["x"]])
            y = np.concatenate([e0["y"], er["y"]])
            s = np.concatenate([e0["sec"], er["sec"]])
            ns = np.concatenate([e0["nsec"], er["nsec"]])
            p = np.concatenate([e0["p"], er["p"]])
    t = s.astype(np.int64) * 1_000_000_000 + ns.astype(np.int64)
    return EventArray(sec * 1_000_000_000 + nsec, width, height,
                      np.asarray(x, np.uint16), np.asarray(y, np.uint16), t,
                      np.where(np.asarray(p) != 0, 1, -1).astype(np.int8))


def make_typestore(ros2: bool):
    """A rosbags typestore with the standard messages and the event messages registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    types: dict = {}
    for name, text in MESSAGE_DEFINITIONS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


@dataclass
class _Topic:
    name: str
    msgtype: str
    connections: list


@dataclass
class _Image:
    """What the index pass knows of one image message (no pixels)."""

    stamp_ns: int
    width: int
    height: int


class RosbagRecording(ChunkedRecording):
    """A ROS 1 (``.bag``) or ROS 2 (folder, ``.db3``, ``.mcap``) bag: events (chunked by
    messages) and, when it has an image topic, frames."""

    def __init__(self, path: Path, fmt: str, options: ReadOptions) -> None:
        from . import require

        require("rosbags", path=path)
        self._ros2 = fmt == "rosbag2"
        warnings: list[str] = []
        if options.time_unit not in (None, "ns"):
            warnings.append(f"`time_unit={options.time_unit!r}` ignored: ROS times are "
                            "seconds and nanoseconds by specification")
        if options.columns is not None or options.one_based:
            warnings.append("`columns` and `one_based` ignored: ROS event messages name their "
                            "fields")
        self.path = Path(path)
        self._reader = self._open()
        try:
            self._store = self._typestore()
            self._events, self._image, self._exposure = self._choose(options.topics)
            self._sub = SubMicrosecond()
            self._images: list[_Image] = []
            self._checked = False
            first = self._first_array()
            width, height = (first.width, first.height) if first is not None else (0, 0)
            if not (width and height):
                width, height = None, None  # type: ignore[assignment]
            if options.sensor is not None:
                if width and (width, height) != tuple(options.sensor):
                    warnings.append(f"`sensor={tuple(options.sensor)}` ignored: the event "
                                    f"messages say {width}x{height}")
                elif not width:
                    width, height = options.sensor
            self._note_images(warnings)
            if not width and self._images:
                width, height = self._images[0].width, self._images[0].height
                warnings.append(f"the event messages state no sensor size; using {width}x"
                                f"{height} from the images (pass `sensor=(W, H)` to set it)")
            super().__init__(self.path, fmt, width, height, warnings)
            self._build_index(self._decode(0, None, index=True))
            self._windows = self._exposures(options)
            if self._images and (self._images[0].width, self._images[0].height) != (
                    self.width, self.height):
                im = self._images[0]
                self.warnings.append(f"the images are {im.width}x{im.height}, not the "
                                     f"{self.width}x{self.height} sensor of the events")
            note = self._sub.note()
            if note:
                self.warnings.append(note)
        except BaseException:
            self._close_reader()
            raise
        #: how to give exposure times, for messages about frames without them
        self.exposure_hint = EXPOSURE_HINT

    # -- the bag ------------------------------------------------------------------------------

    def _open(self):
        if self._ros2:
            from rosbags.rosbag2 import Reader
        else:
            from rosbags.rosbag1 import Reader
        try:
            reader = Reader(self.path)
            reader.open()
        except Exception as e:  # noqa: BLE001 - rosbags raises many kinds on a damaged bag
            raise FormatError(f"cannot be opened as a ROS {'2' if self._ros2 else '1'} bag: "
                              f"{_reason(e)}", path=self.path, hint=self._damaged(e)) from None
        return reader

    def _damaged(self, e: BaseException) -> str:
        if "not indexed" in str(e).lower() or "index" in str(e).lower():
            return ("the recording was cut short before its index was written: `rosbag reindex "
                    "FILE` (ROS 1) rebuilds it from what was recorded, on a copy")
        return _DAMAGED

    def _close_reader(self) -> None:
        reader, self._reader = getattr(self, "_reader", None), None
        if reader is not None:
            try:
                reader.close()
            except Exception:  # noqa: BLE001 - closing a damaged bag
                pass

    def close(self) -> None:
        super().close()
        self._close_reader()

    def _typestore(self):
        """Our definitions, and the bag's own where it stores them (ROS 1 always does)."""
        from rosbags.interfaces import MessageDefinitionFormat
        from rosbags.typesys import get_types_from_idl, get_types_from_msg

        store = make_typestore(self._ros2)
        for conn in self._reader.connections:
            if conn.msgtype not in EVENT_TYPES + IMAGE_TYPES + EXPOSURE_TYPES:
                continue
            try:
                if conn.msgdef.format == MessageDefinitionFormat.MSG and conn.msgdef.data:
                    store.register(get_types_from_msg(conn.msgdef.data, conn.msgtype))
                elif conn.msgdef.format == MessageDefinitionFormat.IDL and conn.msgdef.data:
                    store.register(get_types_from_idl(conn.msgdef.data))
            except Exception:  # noqa: BLE001 - a definition that clashes: ours are kept
                pass
        return store

    def _messages(self, topic: _Topic, start: int | None = None, reader=None):
        """(connection, bag time ns, raw bytes) of ``topic`` from ``start`` on; ``reader``: a
        reader of its own (two message iterations at once must not share one)."""
        try:
            yield from (reader or self._reader).messages(connections=topic.connections,
                                                         start=start)
        except Exception as e:  # noqa: BLE001
            raise FormatError(f"a message of {topic.name} cannot be read ({_reason(e)}): the "
                              "bag is truncated or corrupt", path=self.path,
                              hint=self._damaged(e)) from None

    def _deserialize(self, raw, msgtype: str, topic: str):
        try:
            if self._ros2:
                return self._store.deserialize_cdr(raw, msgtype)
            return self._store.deserialize_ros1(raw, msgtype)
        except Exception as e:  # noqa: BLE001
            raise FormatError(f"a {msgtype} message of {topic} cannot be decoded "
                              f"({_reason(e)})", path=self.path, hint=_DAMAGED) from None

    # -- topics -------------------------------------------------------------------------------

    def _choose(self, wanted: Sequence[str] | None
                ) -> tuple[_Topic, _Topic | None, _Topic | None]:
        topics: dict[str, _Topic] = {}
        for conn in self._reader.connections:
            t = topics.setdefault(conn.topic, _Topic(conn.topic, conn.msgtype, []))
            t.connections.append(conn)
        listing = ", ".join(f"{t.name} ({t.msgtype.replace('/msg/', '/')})"
                            for t in topics.values()) or "none"
        if wanted:
            missing = [w for w in wanted if w not in topics]
            if missing:
                raise InputError(f"the bag has no topic {missing[0]} (its topics: {listing})",
                                 path=self.path, hint="pass `topics` with names it holds")
            chosen = [topics[w] for w in wanted]
            for t in chosen:
                if t.msgtype not in EVENT_TYPES + IMAGE_TYPES + EXPOSURE_TYPES:
                    raise InputError(f"topic {t.name} holds {t.msgtype.replace('/msg/', '/')}, "
                                     "not events, images or exposure times", path=self.path,
                                     hint="pass `topics` naming an EventArray topic, and an "
                                          "Image topic and its exposure topic if wanted")
            events = [t for t in chosen if t.msgtype in EVENT_TYPES]
            images = [t for t in chosen if t.msgtype in IMAGE_TYPES]
            exposure = [t for t in chosen if t.msgtype in EXPOSURE_TYPES]
            for what, found in (("event", events), ("image", images),
                                ("exposure", exposure)):
                if len(found) > 1:
                    raise InputError(f"`topics` names {len(found)} {what} topics "
                                     f"({', '.join(t.name for t in found)}); one is read",
                                     path=self.path, hint="pass `topics` with one of each")
            if not events:
                raise InputError("`topics` names no event topic (dvs_msgs/EventArray or "
                                 f"prophesee_event_msgs/EventArray); the bag has: {listing}",
                                 path=self.path, hint="add the event topic to `topics`")
            return events[0], (images or [None])[0], (exposure or [None])[0]
        events = [t for t in topics.values() if t.msgtype in EVENT_TYPES]
        if not events:
            unknown = [t for t in topics.values() if "event" in t.msgtype.lower()]
            what = (f"; {unknown[0].name} holds {unknown[0].msgtype.replace('/msg/', '/')}, "
                    "which trmd does not read") if unknown else ""
            raise FormatError(f"the bag holds no dvs_msgs/EventArray or "
                              f"prophesee_event_msgs/EventArray topic{what} (its topics: "
                              f"{listing})", path=self.path,
                              hint="record the events with rpg_dvs_ros or a Prophesee ROS "
                                   "driver, or convert them")
        if len(events) > 1:
            raise InputError(f"the bag holds {len(events)} event topics "
                             f"({', '.join(t.name for t in events)})", path=self.path,
                             hint=f"pass `topics` to choose, e.g. `topics={events[0].name}`")
        ev = events[0]
        space = ev.name.rsplit("/", 1)[0]
        images = [t for t in topics.values() if t.msgtype in IMAGE_TYPES]
        if len(images) > 1:
            near = [t for t in images if t.name.rsplit("/", 1)[0] == space]
            if len(near) != 1:
                raise InputError(f"the bag holds {len(images)} image topics "
                                 f"({', '.join(t.name for t in images)})", path=self.path,
                                 hint=f"pass `topics` to choose, e.g. `topics={ev.name},"
                                      f"{images[0].name}`")
            images = near
        image = images[0] if images else None
        exposure = None
        if image is not None:
            home = image.name.rsplit("/", 1)[0]
            cands = [t for t in topics.values() if t.msgtype in EXPOSURE_TYPES
                     and t.name.rsplit("/", 1)[-1] == "exposure"]
            near = [t for t in cands if t.name.rsplit("/", 1)[0] == home]
            pick = near if near else cands
            exposure = pick[0] if len(pick) == 1 else None
        return ev, image, exposure

    # -- events -------------------------------------------------------------------------------

    def _array(self, raw) -> EventArray:
        try:
            arr = decode_event_array(raw, self._ros2)
        except ValueError as e:
            raise FormatError(f"an event message of {self._events.name} is not a "
                              f"{self._events.msgtype.replace('/msg/', '/')} ({e}): truncated "
                              "or another message layout", path=self.path,
                              hint=_DAMAGED) from None
        if not self._checked and len(arr.t_ns):
            self._check_layout(raw, arr)
        return arr

    def _check_layout(self, raw, arr: EventArray) -> None:
        """The numpy decoding agrees with rosbags' on the first message with events."""
        msg = self._deserialize(raw, self._events.msgtype, self._events.name)
        self._checked = True
        evs = msg.events
        ok = len(evs) == len(arr.t_ns)
        for i in (0, len(evs) - 1) if ok else ():
            e = evs[i]
            t = int(e.ts.sec) * 1_000_000_000 + int(e.ts.nanosec)
            ok = ok and (int(e.x), int(e.y), t, 1 if e.polarity else -1) == (
                int(arr.x[i]), int(arr.y[i]), int(arr.t_ns[i]), int(arr.p[i]))
        if not ok:
            raise FormatError(f"the event messages of {self._events.name} do not have the "
                              f"{self._events.msgtype.replace('/msg/', '/')} layout trmd "
                              "reads (x, y, ts, polarity)", path=self.path,
                              hint="convert the bag's events with the driver's tools")

    def _first_array(self) -> EventArray | None:
        messages = self._messages(self._events)
        try:
            for _, _, raw in messages:
                return self._array(raw)
        finally:
            messages.close()
        return None

    def _decode(self, start: int = 0, resume: Any = None, *, index: bool = False
                ) -> Iterator[Chunk]:
        """Chunks of whole event messages; a chunk starts only where the bag time grows, so
        ``resume`` (its first message's bag time, ns) finds it again."""
        k = 0 if resume is None else start
        parts: list[EventArray] = []
        n = 0
        first_time: int | None = None
        last_time: int | None = None

        def flush() -> Chunk:
            t_ns = np.concatenate([q.t_ns for q in parts])
            if index:
                self._sub.add(t_ns)
            return Chunk(k, np.concatenate([q.x for q in parts]),
                         np.concatenate([q.y for q in parts]), ns_to_us(t_ns),
                         np.concatenate([q.p for q in parts]), first_time)

        for _, bag_time, raw in self._messages(self._events, resume):
            if parts and n >= ROS_CHUNK_EVENTS and bag_time > last_time:  # type: ignore[operator]
                if resume is not None or k >= start:
                    yield flush()
                parts, n, k = [], 0, k + 1
            arr = self._array(raw)
            if not parts:
                first_time = bag_time
            parts.append(arr)
            n += len(arr.t_ns)
            last_time = bag_time
        if parts and (resume is not None or k >= start):
            yield flush()

    # -- frames -------------------------------------------------------------------------------

    def _note_images(self, warnings: list[str]) -> None:
        if self._image is None:
            return
        for _, _, raw in self._messages(self._image):
            msg = self._deserialize(raw, self._image.msgtype, self._image.name)
            stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
            if self._image.msgtype.endswith("CompressedImage"):
                h, w = self._pixels(msg).shape[:2]
            else:
                h, w = int(msg.height), int(msg.width)
            self._images.append(_Image(stamp, w, h))
        self._sub.add(np.array([im.stamp_ns for im in self._images], np.int64))

    def _exposures(self, options: ReadOptions) -> list[Exposure | None]:
        stamps = [int(ns_to_us(np.int64(im.stamp_ns))) for im in self._images]
        lengths: list[int | None] | None = None
        where = "the bag"
        if self._exposure is not None and self._images:
            where = f"the bag's {self._exposure.name} topic"
            values = [int(self._deserialize(raw, self._exposure.msgtype,
                                            self._exposure.name).data)
                      for _, _, raw in self._messages(self._exposure)]
            if len(values) == len(self._images):
                lengths = list(values)
            else:
                self.warnings.append(f"{self._exposure.name} holds {len(values)} exposure "
                                     f"times for {len(self._images)} images: they cannot be "
                                     "paired, so it is not used")
            if options.stamp is None:
                self.warnings.append(f"the bag has an exposure topic ({self._exposure.name}) as "
                                     "rpg_dvs_ros writes, whose image stamps mark the middle of "
                                     "the exposure: the stamps are read as its start (the "
                                     "default); pass `stamp='middle'` for such bags")
        windows, notes = stamped_exposures(stamps, lengths, options.exposure_length_us,
                                           options.stamp, stored=where)
        self.warnings.extend(notes)
        return windows

    def _pixels(self, msg) -> np.ndarray:
        """An Image / CompressedImage message's pixels as stored (uint8/uint16 arrays)."""
        name = self._image.name if self._image else "?"
        data = np.asarray(msg.data, np.uint8)
        if hasattr(msg, "encoding"):
            enc = str(msg.encoding).lower()
            h, w, step = int(msg.height), int(msg.width), int(msg.step)
            layouts = {"mono8": (1, 1), "8uc1": (1, 1), "mono16": (1, 2), "16uc1": (1, 2),
                       "rgb8": (3, 1), "bgr8": (3, 1), "8uc3": (3, 1), "rgba8": (4, 1),
                       "bgra8": (4, 1), "8uc4": (4, 1), "rgb16": (3, 2), "bgr16": (3, 2)}
            if enc not in layouts:
                raise FormatError(f"images of {name} have the encoding {msg.encoding!r}, which "
                                  "trmd does not read", path=self.path,
                                  hint="supported: mono8, mono16, rgb8, bgr8, rgba8, bgra8, "
                                       "8UC1/3/4, 16UC1")
            ch, size = layouts[enc]
            if step < w * ch * size or len(data) < step * h:
                raise FormatError(f"an image of {name} holds {len(data)} bytes, too few for "
                                  f"{w}x{h} {msg.encoding}", path=self.path, hint=_DAMAGED)
            rows = data[:step * h].reshape(h, step)[:, :w * ch * size]
            if size == 2:
                rows = np.ascontiguousarray(rows).view(">u2" if msg.is_bigendian else "<u2")
            return rows.reshape(h, w) if ch == 1 else rows.reshape(h, w, ch)
        import cv2

        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        if img is None:
            raise FormatError(f"a compressed image of {name} ({msg.format!r}) cannot be "
                              "decoded", path=self.path, hint=_DAMAGED)
        return img

    def _image_float(self, msg) -> np.ndarray:
        px = self._pixels(msg)
        if hasattr(msg, "encoding"):
            enc = str(msg.encoding).lower()
            order = "gray" if px.ndim == 2 else ("bgr" if enc.startswith(("bgr", "8uc")) else
                                                 "rgb")
            if px.ndim == 3 and px.shape[2] == 4:
                order += "a"
        else:  # OpenCV decodes to BGR(A)
            order = "gray" if px.ndim == 2 else ("bgra" if px.shape[2] == 4 else "bgr")
        return pixels_to_float(px, order, path=self.path)

    def frames(self) -> Iterator[Frame]:
        """The image topic's frames in bag order, decoded one at a time."""
        if self._image is None:
            return
        reader = self._open()  # events may be read meanwhile, through the main reader
        try:
            i = 0
            for _, _, raw in self._messages(self._image, reader=reader):
                if i >= len(self._windows):
                    break
                msg = self._deserialize(raw, self._image.msgtype, self._image.name)
                yield Frame(self._image_float(msg), self._windows[i], i, f"{i:06d}")
                i += 1
        finally:
            reader.close()

    def frame_exposures(self) -> list[Exposure]:
        return [w for w in self._windows if w is not None]

    def num_frames(self) -> int:
        return len(self._images)

    @property
    def topics(self) -> dict[str, str | None]:
        """The topics read: ``events``, ``images`` and ``exposure`` (None when absent)."""
        return {"events": self._events.name,
                "images": self._image.name if self._image else None,
                "exposure": self._exposure.name if self._exposure else None}


def _reason(e: BaseException) -> str:
    text = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    return text[:200]


def read_rosbag(path: Path, options: ReadOptions) -> RosbagRecording:
    """Open a ROS 1 or ROS 2 bag: events, and frames with their exposures when it has images."""
    from .sniff import detect_format

    return RosbagRecording(Path(path), detect_format(path), options)
