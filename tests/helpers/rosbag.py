"""Small ROS 1 / ROS 2 bags for the reader's tests, written with ``rosbags``' own writers and
serializers (message objects, not trmd's decoder), from the published message definitions."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: the definitions as the drivers publish them (ROS 1 .msg syntax)
DVS_EVENT = "uint16 x\nuint16 y\ntime ts\nbool polarity\n"
DVS_ARRAY = "std_msgs/Header header\nuint32 height\nuint32 width\ndvs_msgs/Event[] events\n"
PROPHESEE_ARRAY = ("Header header\nuint32 height\nuint32 width\n"
                   "prophesee_event_msgs/Event[] events\n")


def typestore(ros2: bool):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    types: dict = {}
    for pkg, array in (("dvs_msgs", DVS_ARRAY), ("prophesee_event_msgs", PROPHESEE_ARRAY)):
        types.update(get_types_from_msg(DVS_EVENT, f"{pkg}/msg/Event"))
        types.update(get_types_from_msg(array, f"{pkg}/msg/EventArray"))
    store.register(types)
    return store


@dataclass
class Topic:
    """Messages of one topic: (bag time ns, message object) pairs."""

    name: str
    msgtype: str
    messages: list = field(default_factory=list)


class BagBuilder:
    """Builds message objects for one bag version and writes them with rosbags' writer."""

    def __init__(self, ros2: bool) -> None:
        self.ros2 = ros2
        self.store = typestore(ros2)
        self.topics: dict[str, Topic] = {}

    def _t(self, ns: int):
        Time = self.store.types["builtin_interfaces/msg/Time"]
        return Time(sec=int(ns) // 1_000_000_000, nanosec=int(ns) % 1_000_000_000)

    def header(self, ns: int, frame_id: str = "cam", seq: int = 0):
        Header = self.store.types["std_msgs/msg/Header"]
        if self.ros2:
            return Header(stamp=self._t(ns), frame_id=frame_id)
        return Header(seq=seq, stamp=self._t(ns), frame_id=frame_id)

    def topic(self, name: str, msgtype: str) -> Topic:
        return self.topics.setdefault(name, Topic(name, msgtype))

    def events(self, name: str, t_ns, x, y, p, width: int, height: int, bag_ns: int | None = None,
               pkg: str = "dvs_msgs", frame_id: str = "cam") -> None:
        """One EventArray message (polarity: p > 0)."""
        Event = self.store.types[f"{pkg}/msg/Event"]
        Array = self.store.types[f"{pkg}/msg/EventArray"]
        evs = [Event(x=int(a), y=int(b), ts=self._t(int(t)), polarity=bool(c > 0))
               for t, a, b, c in zip(t_ns, x, y, p, strict=True)]
        stamp = int(t_ns[0]) if len(t_ns) else 0
        msg = Array(header=self.header(stamp, frame_id), height=height, width=width, events=evs)
        self.topic(name, f"{pkg}/msg/EventArray").messages.append(
            (stamp if bag_ns is None else bag_ns, msg))

    def image(self, name: str, stamp_ns: int, pixels: np.ndarray, encoding: str = "mono8",
              bag_ns: int | None = None) -> None:
        Image = self.store.types["sensor_msgs/msg/Image"]
        px = np.ascontiguousarray(pixels)
        h, w = px.shape[:2]
        step = px.strides[0]
        msg = Image(header=self.header(stamp_ns), height=h, width=w, encoding=encoding,
                    is_bigendian=0, step=step, data=px.view(np.uint8).ravel())
        self.topic(name, "sensor_msgs/msg/Image").messages.append(
            (stamp_ns if bag_ns is None else bag_ns, msg))

    def compressed(self, name: str, stamp_ns: int, png: bytes, bag_ns: int | None = None) -> None:
        Img = self.store.types["sensor_msgs/msg/CompressedImage"]
        msg = Img(header=self.header(stamp_ns), format="png",
                  data=np.frombuffer(png, np.uint8))
        self.topic(name, "sensor_msgs/msg/CompressedImage").messages.append(
            (stamp_ns if bag_ns is None else bag_ns, msg))

    def int32(self, name: str, value: int, bag_ns: int) -> None:
        Int32 = self.store.types["std_msgs/msg/Int32"]
        self.topic(name, "std_msgs/msg/Int32").messages.append((bag_ns, Int32(data=int(value))))

    def other(self, name: str, bag_ns: int) -> None:
        """An IMU message: a topic the reader leaves alone."""
        s = self.store.types
        Imu = s["sensor_msgs/msg/Imu"]
        q = s["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
        v = s["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        msg = Imu(header=self.header(bag_ns), orientation=q,
                  orientation_covariance=np.zeros(9), angular_velocity=v,
                  angular_velocity_covariance=np.zeros(9), linear_acceleration=v,
                  linear_acceleration_covariance=np.zeros(9))
        self.topic(name, "sensor_msgs/msg/Imu").messages.append((bag_ns, msg))

    def serialize(self, msg, msgtype: str) -> bytes:
        if self.ros2:
            return bytes(self.store.serialize_cdr(msg, msgtype))
        return bytes(self.store.serialize_ros1(msg, msgtype))

    def write(self, path: Path, storage: str = "sqlite3") -> Path:
        """Write every topic's messages in bag-time order; ROS 2: a folder (``storage``:
        sqlite3 or mcap)."""
        items = sorted(((ns, i, t, m) for t in self.topics.values()
                        for i, (ns, m) in enumerate(t.messages)), key=lambda r: (r[0], r[1]))
        if self.ros2:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            writer = Writer(path, version=9, storage_plugin=plugin)
        else:
            from rosbags.rosbag1 import Writer

            writer = Writer(path)
        with writer:
            conns = {t.name: writer.add_connection(t.name, t.msgtype, typestore=self.store)
                     for t in self.topics.values()}
            for ns, _, t, msg in items:
                writer.write(conns[t.name], int(ns), self.serialize(msg, t.msgtype))
        return path


def split(t_ns: Sequence[int], per_message: int) -> list[slice]:
    return [slice(i, i + per_message) for i in range(0, len(t_ns), per_message)]
