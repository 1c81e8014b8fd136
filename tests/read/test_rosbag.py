"""ROS 1 / ROS 2 bags: small bags written with rosbags' own writers and serializers
(:mod:`tests.helpers.rosbag`) read back exactly — events, frames, exposure windows — and damaged
or ambiguous bags give one clear line."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.cli import assert_one_error_line
from tests.helpers.data import assert_events as assert_events_us
from tests.helpers.rosbag import BagBuilder, split
from trmd_cli.cli.app import app
from trmd_cli.errors import FormatError, InputError
from trmd_cli.events import Exposure
from trmd_cli.read import ReadOptions, detect_format, open_events
from trmd_cli.read import chunked as chunked_mod
from trmd_cli.read import rosbag as rosbag_mod

runner = CliRunner()
W, H = 64, 48
T0 = 1_600_000_000_000_000_000  # ns: bags keep Unix time
#: one sub-µs remainder for every time, as a DAVIS driver stamps (reset instant + whole µs)
PHASE = 417

KINDS = ["ros1", "ros2-sqlite3", "ros2-mcap"]


def bag_path(tmp: Path, kind: str, name: str = "rec") -> Path:
    return tmp / (f"{name}.bag" if kind == "ros1" else name)


def write(builder: BagBuilder, path: Path, kind: str) -> Path:
    return builder.write(path, storage="mcap" if kind.endswith("mcap") else "sqlite3")


def random_events(rng, n=3000, span_ns=900_000_000, phase=PHASE):
    t = T0 + np.sort(rng.integers(0, span_ns // 1000, n)) * 1000 + phase
    return (t.astype(np.int64), rng.integers(0, W, n), rng.integers(0, H, n),
            np.where(rng.integers(0, 2, n) == 1, 1, -1))


def davis_bag(kind: str, rng, *, exposure=True, frames=3, per_message=400, images=True):
    """An rpg_dvs_ros-like bag: /dvs/events, /dvs/image_raw (stamped mid-exposure),
    /dvs/exposure (µs), /dvs/imu."""
    b = BagBuilder(kind != "ros1")
    t, x, y, p = random_events(rng)
    for s in split(t, per_message):
        b.events("/dvs/events", t[s], x[s], y[s], p[s], W, H, bag_ns=int(t[s][-1]) + 50_000)
    shots = []
    for k in range(frames if images else 0):
        img = rng.integers(0, 256, (H, W)).astype(np.uint8)
        stamp = T0 + 100_000_000 + 250_000_000 * k + PHASE
        length = 20_000 + k  # µs; odd lengths too
        b.image("/dvs/image_raw", stamp, img, bag_ns=stamp + 30_000_000)
        if exposure:
            b.int32("/dvs/exposure", length, bag_ns=stamp + 30_000_001)
        shots.append((img, stamp, length))
    b.other("/dvs/imu", T0 + 1000)
    return b, (t, x, y, p), shots


def assert_events(stream, t_ns, x, y, p) -> None:
    assert_events_us(stream, t_ns // 1000, x, y, p)


@pytest.mark.parametrize("kind", KINDS)
def test_bag_events_frames_and_exposures_exact(tmp_path, rng, kind):
    b, (t, x, y, p), shots = davis_bag(kind, rng)
    path = write(b, bag_path(tmp_path, kind), kind)
    fmt = "rosbag1" if kind == "ros1" else "rosbag2"
    assert detect_format(path) == fmt
    with open_events(path, ReadOptions(stamp="middle")) as rec:
        assert (rec.format, rec.width, rec.height) == (fmt, W, H)
        assert rec.topics == {"events": "/dvs/events", "images": "/dvs/image_raw",
                              "exposure": "/dvs/exposure"}
        assert rec.warnings == []  # the shared sub-µs remainder is dropped without a word
        assert rec.num_events() == len(t)
        assert rec.time_range_us() == (int(t[0]) // 1000, int(t[-1]) // 1000)
        assert_events(rec.events(), t, x, y, p)
        frames = list(rec.frames())
        assert len(frames) == len(shots) == rec.num_frames()
        for fr, (img, stamp, length) in zip(frames, shots, strict=True):
            # the middle stamp is start + ⌊L/2⌋ µs (libcaer), so the window comes back exactly
            start = stamp // 1000 - length // 2
            assert fr.exposure == Exposure(start, start + length)
            np.testing.assert_array_equal(np.rint(fr.image * 255).astype(int), img)
    with open_events(path) as rec:  # the default reads stamps as the start, and says so
        assert rec.frame_exposures()[0] == Exposure(shots[0][1] // 1000,
                                                    shots[0][1] // 1000 + shots[0][2])
        assert any("`stamp='middle'`" in w for w in rec.warnings)


def test_sub_microsecond_rule(tmp_path, rng):
    """Shared remainders: intervals exact, silently. Mixed ones: floor, and one warning."""
    b = BagBuilder(False)
    t = np.array([T0 + 1_000_999, T0 + 2_000_001, T0 + 2_000_999], np.int64)
    b.events("/e", t, [1, 2, 3], [1, 2, 3], [1, -1, 1], W, H)
    path = b.write(tmp_path / "mixed.bag")
    with open_events(path) as rec:
        np.testing.assert_array_equal(rec.events().t, t // 1000)  # floor, never rounded up
        assert any("finer than a microsecond" in w for w in rec.warnings)


def test_frames_without_exposure_need_exposure_length(tmp_path, rng):
    b, _, shots = davis_bag("ros1", rng, exposure=False)
    path = b.write(tmp_path / "noexp.bag")
    with open_events(path) as rec:
        assert rec.num_frames() == 3 and rec.frame_exposures() == []
        assert any("no exposure time" in w and "`exposure_length_us`" in w
                   for w in rec.warnings)
    with open_events(path, ReadOptions(exposure_length_us=5000)) as rec:
        assert rec.frame_exposures() == [Exposure(s // 1000, s // 1000 + 5000)
                                         for _, s, _ in shots]
    out = tmp_path / "out"
    r = runner.invoke(app, ["deblur", str(path), "-o", str(out), "--method", "edi"])
    assert_one_error_line(r, "noexp.bag", "--exposure-length")
    assert not out.exists()
    r = runner.invoke(app, ["deblur", str(path), "-o", str(out), "--method", "edi",
                            "--exposure-length", "5ms", "--contrast", "0.2"])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in out.iterdir()) == ["000000", "000001", "000002", "meta.json"]


def test_exposure_topic_wins_over_exposure_length(tmp_path, rng):
    b, _, shots = davis_bag("ros2-sqlite3", rng)
    path = b.write(tmp_path / "bag")
    with open_events(path, ReadOptions(exposure_length_us=1, stamp="start")) as rec:
        assert [w.duration_us for w in rec.frame_exposures()] == [s[2] for s in shots]
        assert any("`exposure_length_us` ignored" in w for w in rec.warnings)


def test_topics_are_chosen_or_asked_for(tmp_path, rng):
    b = BagBuilder(False)
    t, x, y, p = random_events(rng, 200)
    b.events("/left/events", t, x, y, p, W, H)
    b.events("/right/events", t[:50], x[:50], y[:50], p[:50], W, H,
             pkg="prophesee_event_msgs")
    b.image("/left/image_raw", int(t[10]), np.zeros((H, W), np.uint8))
    b.image("/right/image_raw", int(t[10]), np.full((H, W), 7, np.uint8))
    path = b.write(tmp_path / "stereo.bag")
    with pytest.raises(InputError, match=r"2 event topics \(/left/events, /right/events\)"):
        open_events(path)
    r = runner.invoke(app, ["info", str(path)])
    assert_one_error_line(r, "stereo.bag", "--topics /left/events")
    with open_events(path, ReadOptions(topics=("/right/events",))) as rec:
        assert rec.num_events() == 50 and rec.topics["images"] is None
        assert_events(rec.events(), t[:50], x[:50], y[:50], p[:50])
    with open_events(path, ReadOptions(topics=("/left/events", "/right/image_raw"),
                                       exposure_length_us=100)) as rec:
        assert rec.num_events() == 200
        assert float(next(rec.frames()).image.max()) == pytest.approx(7 / 255)
    with pytest.raises(InputError, match="no topic /nope .*its topics: /left/events"):
        open_events(path, ReadOptions(topics=("/nope",)))
    with pytest.raises(InputError, match="names 2 event topics"):
        open_events(path, ReadOptions(topics=("/left/events", "/right/events")))


def test_a_bag_without_events_is_refused(tmp_path):
    b = BagBuilder(False)
    b.other("/imu", T0)
    path = b.write(tmp_path / "imu.bag")
    r = runner.invoke(app, ["info", str(path)])
    assert_one_error_line(r, "imu.bag", "no dvs_msgs/EventArray")


@pytest.mark.parametrize("kind", ["ros1", "ros2-mcap"])
def test_bag_streams_by_chunks_and_seeks_by_bag_time(tmp_path, rng, kind, monkeypatch):
    monkeypatch.setattr(chunked_mod, "CACHE_MAX_EVENTS", 0)
    monkeypatch.setattr(rosbag_mod, "ROS_CHUNK_EVENTS", 500)
    b, (t, x, y, p), _ = davis_bag(kind, rng, per_message=120)
    path = write(b, bag_path(tmp_path, kind), kind)
    tu = t // 1000
    with open_events(path) as rec:
        assert len(rec._first) >= 5
        for lo, hi in [(tu[2500], tu[2600]), (tu[10], tu[40]), (tu[1200], tu[2999] + 1),
                       (tu[100], tu[150])]:
            sel = (tu >= lo) & (tu < hi)
            assert_events(rec.events(lo, hi), t[sel], x[sel], y[sel], p[sel])
        assert sum(len(c) for c in rec.iter_chunks(max_events=333)) == len(t)


@pytest.mark.parametrize("encoding,shape,dtype", [("mono16", (H, W), np.uint16),
                                                  ("rgb8", (H, W, 3), np.uint8),
                                                  ("bgra8", (H, W, 4), np.uint8)])
def test_image_encodings(tmp_path, rng, encoding, shape, dtype):
    b = BagBuilder(True)
    t, x, y, p = random_events(rng, 50)
    b.events("/dvs/events", t, x, y, p, W, H)
    px = rng.integers(0, np.iinfo(dtype).max, shape).astype(dtype)
    b.image("/dvs/image_raw", int(t[5]), px, encoding=encoding)
    path = b.write(tmp_path / "bag")
    with open_events(path, ReadOptions(exposure_length_us=10)) as rec:
        img = next(rec.frames()).image
    scale = 65535 if dtype == np.uint16 else 255
    want = px if px.ndim == 2 else px[..., :3]
    if encoding.startswith("bgr"):
        want = want[..., ::-1]
    np.testing.assert_array_equal(np.rint(img * scale).astype(int), want)


def test_compressed_images(tmp_path, rng):
    b = BagBuilder(False)
    t, x, y, p = random_events(rng, 50)
    b.events("/cam/events", t, x, y, p, W, H)
    img = rng.integers(0, 256, (H, W)).astype(np.uint8)
    b.compressed("/cam/image_raw/compressed", int(t[3]), cv2.imencode(".png", img)[1].tobytes())
    path = b.write(tmp_path / "c.bag")
    with open_events(path, ReadOptions(exposure_length_us=10)) as rec:
        np.testing.assert_array_equal(np.rint(next(rec.frames()).image * 255), img)


@pytest.mark.parametrize("ros2", [False, True])
def test_numpy_decoding_matches_rosbags(ros2, rng):
    """Every alignment case: frame ids of 0–4 characters, 0–3 events, both CDR byte orders."""
    from rosbags.typesys import Stores  # noqa: F401 - rosbags present

    b = BagBuilder(ros2)
    for n in (0, 1, 2, 3, 17):
        for frame_id in ("", "a", "ab", "abc", "abcd"):
            t, x, y, p = random_events(rng, n, phase=int(rng.integers(0, 1000)))
            b.events("/e", t, x, y, p, 346, 260, frame_id=frame_id)
            _, msg = b.topics["/e"].messages[-1]
            blobs = [b.serialize(msg, "dvs_msgs/msg/EventArray")]
            if ros2:
                blobs.append(bytes(b.store.serialize_cdr(msg, "dvs_msgs/msg/EventArray",
                                                         little_endian=False)))
            for raw in blobs:
                arr = rosbag_mod.decode_event_array(raw, ros2)
                assert (arr.width, arr.height) == (346, 260)
                np.testing.assert_array_equal(arr.t_ns, t)
                np.testing.assert_array_equal(arr.x, x)
                np.testing.assert_array_equal(arr.y, y)
                np.testing.assert_array_equal(arr.p, p)


def test_truncated_bags_are_one_clear_error(tmp_path, rng):
    b, _, _ = davis_bag("ros1", rng)
    good = b.write(tmp_path / "good.bag")
    data = good.read_bytes()
    for frac in (0.5, 0.97):
        cut = tmp_path / f"cut{int(frac * 100)}.bag"
        cut.write_bytes(data[: int(len(data) * frac)])
        with pytest.raises(FormatError) as e:
            with open_events(cut) as rec:
                rec.events()
        assert e.value.path == str(cut) and e.value.hint
        r = runner.invoke(app, ["convert", str(cut), "-o", str(tmp_path / "o.npz")])
        assert_one_error_line(r, cut.name, "ROS 1 bag|truncated|corrupt")
        assert not (tmp_path / "o.npz").exists()
    b2, _, _ = davis_bag("ros2-sqlite3", rng)
    folder = b2.write(tmp_path / "bag2")
    db = next(folder.glob("*.db3"))
    db.write_bytes(db.read_bytes()[:4096])
    r = runner.invoke(app, ["info", str(folder)])
    assert_one_error_line(r, "bag2", "ROS 2 bag|truncated|corrupt")
    only = tmp_path / "only"
    only.mkdir()
    shutil.copy(db, only / db.name)
    r = runner.invoke(app, ["info", str(only)])
    assert_one_error_line(r, "only", "no metadata.yaml")


def test_missing_rosbags_names_the_extra(tmp_path, rng, monkeypatch):
    b, _, _ = davis_bag("ros1", rng, images=False)
    path = b.write(tmp_path / "r.bag")
    import sys

    monkeypatch.setitem(sys.modules, "rosbags", None)  # as if not installed
    r = runner.invoke(app, ["info", str(path)])
    assert_one_error_line(r, "r.bag", r"pip install 'trmd\[formats\]'")


def test_deblur_and_hfr_run_on_a_bag(tmp_path, rng):
    b, _, _ = davis_bag("ros2-sqlite3", rng)
    path = b.write(tmp_path / "bag")
    out = tmp_path / "out"
    r = runner.invoke(app, ["deblur", str(path), "-o", str(out), "--method", "edi",
                            "--stamp", "middle", "--contrast", "0.2"])
    assert r.exit_code == 0, r.output
    assert (out / "000002" / "sharp.png").is_file()
    r = runner.invoke(app, ["hfr", str(path), "-o", str(tmp_path / "v"), "--method", "edi",
                            "--stamp", "middle", "--contrast", "0.2", "--no-fill-gaps"])
    assert r.exit_code == 0, r.output
