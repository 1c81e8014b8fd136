"""Peak memory of reading a large ROS bag: `trmd info`, and every frame's window of events.

Run::

    python bench/bench_rosbag.py                 # a ROS 1 bag of 20 M events (≈ 290 MB)
    python bench/bench_rosbag.py --ros2          # … and the same as a ROS 2 bag (sqlite3)
    python bench/bench_rosbag.py --events 2e6    # smaller: a quick check
    python bench/bench_rosbag.py --dir /work/runs --keep

The bag is written in a fresh temporary folder with ``rosbags``' writer, an rpg_dvs_ros layout:
``/dvs/events`` (``dvs_msgs/EventArray``, 240×180, 50 000 events per message — serialized here
with numpy, the message layout checked against rosbags' own decoder on the first message),
``/dvs/image_raw`` (mono8, one every 33 ms, stamped mid-exposure) and ``/dvs/exposure``
(``std_msgs/Int32``, 10 ms). Then, each in a child process that writes its own peak resident
memory (``VmHWM``) when it exits (see bench_memory.py for why not ``ru_maxrss``):

* ``trmd info BAG --stamp middle`` — statistics over every event, streamed in chunks;
* windows — ``open_events`` and ``iter_windows`` over every frame's exposure: what ``trmd
  deblur`` asks of the reader, without the deblurring;
* whole — ``rec.events()``: every event in memory at once, for comparison.

The claim (issue: a multi-GB bag must not be loaded whole): the first two stay far below the
third, and do not grow with the bag. Nothing is written inside the repository.
"""

from __future__ import annotations

import argparse
import shutil
import struct
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _common import machine, run_peak  # noqa: E402

W, H = 240, 180
PER_MESSAGE = 50_000
RATE = 2_000_000  # events per second
FRAME_US = 33_000
EXPOSURE_US = 10_000
T0_NS = 1_600_000_000_000_000_000 + 417  # Unix time, one sub-µs remainder as a driver has

_EV1 = np.dtype({"names": ["x", "y", "sec", "nsec", "p"],
                 "formats": ["<u2", "<u2", "<u4", "<u4", "u1"],
                 "offsets": [0, 2, 4, 8, 12], "itemsize": 13})


def ros1_event_array(seq: int, t_ns: np.ndarray, x, y, p) -> bytes:
    """A ROS 1 serialized dvs_msgs/EventArray: Header (seq, stamp, frame_id), height, width,
    then packed events (uint16 x, uint16 y, time ts, bool polarity)."""
    frame = b"dvs"
    stamp = int(t_ns[0])
    head = struct.pack("<III", seq, stamp // 10**9, stamp % 10**9)
    head += struct.pack("<I", len(frame)) + frame + struct.pack("<III", H, W, len(t_ns))
    ev = np.empty(len(t_ns), _EV1)
    ev["x"], ev["y"] = x, y
    ev["sec"], ev["nsec"] = t_ns // 10**9, t_ns % 10**9
    ev["p"] = p
    return head + ev.tobytes()


def cdr_event_array(t_ns: np.ndarray, x, y, p) -> bytes:
    """The same message in little-endian CDR (ROS 2): the first event 4-aligned, later ones 16
    bytes apart with two padding bytes before ``ts``."""
    frame = b"dvs\x00"
    stamp = int(t_ns[0])
    body = struct.pack("<iI", stamp // 10**9, stamp % 10**9) + struct.pack("<I", len(frame))
    body += frame
    body += b"\x00" * (-len(body) % 4) + struct.pack("<III", H, W, len(t_ns))
    n = len(t_ns)
    out = np.zeros(13 + 16 * (n - 1) if n else 0, np.uint8)
    rec = np.zeros(n, np.dtype({"names": ["x", "y", "sec", "nsec", "p"],
                                "formats": ["<u2", "<u2", "<i4", "<u4", "u1"],
                                "offsets": [0, 2, 6, 10, 14], "itemsize": 16}))
    rec["x"], rec["y"], rec["sec"], rec["nsec"], rec["p"] = x, y, t_ns // 10**9, t_ns % 10**9, p
    flat = rec.view(np.uint8).reshape(n, 16)
    out[:13] = np.concatenate([flat[0, :4], flat[0, 6:15]])
    if n > 1:
        out[14:] = flat[1:].reshape(-1)[: len(out) - 14]
    return b"\x00\x01\x00\x00" + body + out.tobytes()


def write_bag(path: Path, events: int, ros2: bool, seed: int = 0) -> dict:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    store.register(get_types_from_msg("uint16 x\nuint16 y\ntime ts\nbool polarity\n",
                                      "dvs_msgs/msg/Event"))
    store.register(get_types_from_msg("std_msgs/Header header\nuint32 height\nuint32 width\n"
                                      "dvs_msgs/Event[] events\n", "dvs_msgs/msg/EventArray"))
    if ros2:
        from rosbags.rosbag2 import Writer

        writer = Writer(path, version=9)
    else:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    rng = np.random.default_rng(seed)
    Image, Header = store.types["sensor_msgs/msg/Image"], store.types["std_msgs/msg/Header"]
    Time, Int32 = store.types["builtin_interfaces/msg/Time"], store.types["std_msgs/msg/Int32"]
    ser = store.serialize_cdr if ros2 else store.serialize_ros1
    span_ns = int(events / RATE * 1e9)
    yy, xx = np.mgrid[0:H, 0:W]
    base = ((xx // 12 + yy // 12) % 2 * 150 + 50).astype(np.uint8)
    frames = 0
    with writer:
        ev = writer.add_connection("/dvs/events", "dvs_msgs/msg/EventArray", typestore=store)
        im = writer.add_connection("/dvs/image_raw", "sensor_msgs/msg/Image", typestore=store)
        ex = writer.add_connection("/dvs/exposure", "std_msgs/msg/Int32", typestore=store)
        next_frame = FRAME_US * 1000
        for seq, i in enumerate(range(0, events, PER_MESSAGE)):
            n = min(PER_MESSAGE, events - i)
            lo = i * span_ns // events
            hi = (i + n) * span_ns // events
            t = T0_NS + np.sort(rng.integers(lo // 1000, max(hi // 1000, lo // 1000 + 1), n)) \
                * 1000
            x = rng.integers(0, W, n, dtype=np.uint16)
            y = rng.integers(0, H, n, dtype=np.uint16)
            p = rng.integers(0, 2, n, dtype=np.uint8)
            raw = cdr_event_array(t, x, y, p) if ros2 else ros1_event_array(seq, t, x, y, p)
            if seq == 0:  # the numpy serialization is the message rosbags knows
                msg = (store.deserialize_cdr if ros2 else store.deserialize_ros1)(
                    raw, "dvs_msgs/msg/EventArray")
                e = msg.events[-1]
                assert (e.x, e.y, e.ts.sec * 10**9 + e.ts.nanosec, bool(e.polarity)) == (
                    x[-1], y[-1], t[-1], bool(p[-1])), "serialization does not match rosbags"
            writer.write(ev, int(t[-1]) + 1_000_000, raw)
            while next_frame <= hi:
                stamp = T0_NS + next_frame  # the middle of a 10 ms exposure
                sec, nsec = divmod(stamp, 10**9)
                kw = {} if ros2 else {"seq": frames}
                img = Image(header=Header(stamp=Time(sec=sec, nanosec=nsec), frame_id="dvs",
                                          **kw), height=H, width=W, encoding="mono8",
                            is_bigendian=0, step=W, data=np.roll(base, frames, 1).ravel())
                writer.write(im, stamp + 20_000_000, bytes(ser(img, "sensor_msgs/msg/Image")))
                writer.write(ex, stamp + 20_000_001,
                             bytes(ser(Int32(data=EXPOSURE_US), "std_msgs/msg/Int32")))
                frames += 1
                next_frame += FRAME_US * 1000
    size = sum(f.stat().st_size for f in path.rglob("*")) if path.is_dir() else \
        path.stat().st_size
    return {"frames": frames, "bytes": size}


WINDOWS = """
from trmd_cli.read import ReadOptions, open_events
with open_events({bag!r}, ReadOptions(stamp="middle")) as rec:
    wins = rec.frame_exposures()
    n = sum(len(ev) for ev in rec.iter_windows(wins))
print(len(wins), n)
"""

WHOLE = """
from trmd_cli.read import open_events
with open_events({bag!r}) as rec:
    print(len(rec.events()))
"""


def run(args: list[str], work: Path) -> dict:
    peak, wall, stdout = run_peak(args, work / "hwm")
    return {"peak_mib": peak, "wall_s": wall, "stdout": stdout}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--events", type=float, default=20e6, help="events in the bag (default 20M)")
    ap.add_argument("--ros2", action="store_true", help="also a ROS 2 bag (sqlite3)")
    ap.add_argument("--dir", type=Path, default=None,
                    help="where to put the temporary folder (default: $TMPDIR or /tmp)")
    ap.add_argument("--keep", action="store_true", help="keep the bags")
    args = ap.parse_args()
    events = int(args.events)
    repo = Path(__file__).resolve().parents[1]
    if args.dir is not None:
        args.dir.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="trmd-bench-rosbag-", dir=args.dir))
    if repo in work.resolve().parents:
        shutil.rmtree(work)
        raise SystemExit(f"refusing to write bags inside the repository ({work})")
    print(machine())
    print(f"{events:,} events at {W}x{H}, {PER_MESSAGE:,} per message, a frame every "
          f"{FRAME_US // 1000} ms; in {work}")
    print(f"{'bag':>6} {'MB':>6} {'frames':>6} {'write s':>8} | {'info s':>7} {'MiB':>5} | "
          f"{'windows s':>9} {'MiB':>5} | {'whole s':>7} {'MiB':>5}")
    try:
        for ros2 in ([False, True] if args.ros2 else [False]):
            bag = work / ("bag2" if ros2 else "bag.bag")
            t0 = time.perf_counter()
            made = write_bag(bag, events, ros2)
            t_write = time.perf_counter() - t0
            info = run(["info", str(bag), "--stamp", "middle", "--json"], work)
            if f'"events": {events}' not in info["stdout"]:
                raise SystemExit(f"trmd info did not count {events} events:\n{info['stdout']}")
            win = run(["--snippet", WINDOWS.format(bag=str(bag))], work)
            frames, in_windows = map(int, win["stdout"].split())
            if frames != made["frames"] or in_windows <= 0:
                raise SystemExit(f"windows: {win['stdout']} (expected {made['frames']} frames)")
            whole = run(["--snippet", WHOLE.format(bag=str(bag))], work)
            if int(whole["stdout"]) != events:
                raise SystemExit(f"whole read gave {whole['stdout']} events")
            print(f"{'ROS 2' if ros2 else 'ROS 1':>6} {made['bytes'] / 1e6:6.0f} "
                  f"{made['frames']:6d} {t_write:8.1f} | {info['wall_s']:7.1f} "
                  f"{info['peak_mib']:5.0f} | {win['wall_s']:9.1f} {win['peak_mib']:5.0f} | "
                  f"{whole['wall_s']:7.1f} {whole['peak_mib']:5.0f}", flush=True)
            if not args.keep:
                shutil.rmtree(bag) if bag.is_dir() else bag.unlink()
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
