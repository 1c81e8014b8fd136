"""Text, NumPy and HDF5 readers: layouts, units, round trips, and bad input."""

from __future__ import annotations

import pickle

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.data import random_stream
from trmd_cli.errors import FormatError, InputError
from trmd_cli.events import Exposure, make_stream
from trmd_cli.read import ReadOptions, detect_format, open_events
from trmd_cli.units import to_microseconds
from trmd_cli.write import write_events_npz, write_events_text, write_h5


def _same(a, b):
    for k in "xytp":
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    assert (a.width, a.height) == (b.width, b.height)


# ---------------------------------------------------------------- units
def test_unit_conversion_round_trips():
    us = np.array([0, 1, 999_999, 1_000_000, 123_456_789], np.int64)
    for unit, scale in (("s", 1e6), ("ms", 1e3), ("us", 1)):
        np.testing.assert_array_equal(to_microseconds(us / scale, unit), us)
    np.testing.assert_array_equal(to_microseconds(us * 1000, "ns"), us)
    np.testing.assert_array_equal(to_microseconds(us // 1000, "ms"), us // 1000 * 1000)
    # epoch seconds keep microsecond resolution in float64
    t = 1.6e9 + np.array([0.000001, 0.5, 0.104])
    np.testing.assert_array_equal(to_microseconds(t, None) - 1_600_000_000_000_000,
                                  [1, 500_000, 104_000])


# ---------------------------------------------------------------- text
def test_text_ecd_float_seconds(tmp_path):
    f = tmp_path / "events.txt"
    f.write_text("0.000100 3 4 1\n0.000250 5 6 0\n0.001000 1 2 1\n")
    s = open_events(f, ReadOptions(sensor=(10, 8))).events()
    assert s.t.tolist() == [100, 250, 1000]
    assert s.x.tolist() == [3, 5, 1] and s.y.tolist() == [4, 6, 2]
    assert s.p.tolist() == [1, -1, 1]


def test_text_e2vid_header_size(tmp_path):
    f = tmp_path / "events.txt"
    f.write_text("240 180\n0.5 239 179 1\n0.75 0 0 0\n")
    rec = open_events(f)
    assert rec.sensor_size() == (240, 180) and not rec.warnings
    assert rec.events().t.tolist() == [500_000, 750_000]


def test_text_evdi_integer_us_columns_one_based_header(tmp_path):
    f = tmp_path / "events.csv"
    f.write_text("# recorded by something\ntimestamp,y,x,polarity\n10,1,2,1\n20,3,4,-1\n")
    s = open_events(f, ReadOptions(columns=("t", "y", "x", "p"), one_based=True,
                                   sensor=(5, 5))).events()
    assert s.t.tolist() == [10, 20]
    assert s.x.tolist() == [1, 3] and s.y.tolist() == [0, 2]
    assert s.p.tolist() == [1, -1]


def test_text_time_unit_override(tmp_path):
    f = tmp_path / "e.txt"
    f.write_text("1 0 0 1\n2 0 0 1\n")
    assert open_events(f, ReadOptions(time_unit="ms")).events().t.tolist() == [1000, 2000]
    assert open_events(f).events().t.tolist() == [1, 2]


def test_text_round_trip(tmp_path, rng):
    s = random_stream(rng, n=3000)
    write_events_text(tmp_path / "e.txt", s)
    _same(open_events(tmp_path / "e.txt").events(), s)


@pytest.mark.parametrize("body,msg", [
    ("0.1 1 1 1\n0.05 1 1 1\n", "not sorted"),
    ("0.1 1 1 1\nnan 1 1 1\n", "non-finite"),
    ("-0.1 1 1 1\n", "negative"),
    ("0.1 1 1 1\n0.2 oops 1 1\n", "malformed"),
    # a first line with one bad field is an event line, not a header to skip unsaid
    ("1 1 2 x\n2 3 4 0\n", "malformed event line 1"),
    ("1,1,2,1O\n2,3,4,0\n", "malformed event line 1"),
    ("0.1 1 1\n", "columns"),
    ("0.1 1 1 7\n", "polarity"),
    ("# nothing here\n", "no event lines"),
])
def test_text_bad(tmp_path, body, msg):
    f = tmp_path / "bad.txt"
    f.write_text(body)
    with pytest.raises((InputError, FormatError), match=msg):
        open_events(f)


def test_text_byte_order_mark_and_headers_keep_every_event(tmp_path):
    for name, data in (("bom.txt", b"\xef\xbb\xbf1 1 2 1\n2 3 4 0\n"),
                       ("bom_header.csv", b"\xef\xbb\xbft,x,y,p\n1,1,2,1\n2,3,4,0\n"),
                       ("words.txt", b"Width: 346 Height: 260\n1 1 2 1\n2 3 4 0\n")):
        (tmp_path / name).write_bytes(data)
        s = open_events(tmp_path / name, ReadOptions(sensor=(8, 8))).events()
        assert s.t.tolist() == [1, 2] and s.x.tolist() == [1, 3], name


def test_nanoseconds_floor_to_the_same_microseconds_in_every_format(tmp_path):
    ns = np.array([1500, 2500, 3999, 4000])
    assert to_microseconds(ns, "ns").tolist() == [1, 2, 3, 4]
    assert to_microseconds(ns.astype(np.float64), "ns").tolist() == [1, 2, 3, 4]
    (tmp_path / "ns.txt").write_text("".join(f"{t} 1 2 1\n" for t in ns))
    np.savez(tmp_path / "ns.npz", x=np.ones(4, int), y=np.full(4, 2), t=ns, p=np.ones(4, int))
    for name in ("ns.txt", "ns.npz"):
        s = open_events(tmp_path / name, ReadOptions(time_unit="ns", sensor=(4, 4))).events()
        assert s.t.tolist() == [1, 2, 3, 4], name


def test_files_say_which_unit_their_times_were_read_in(tmp_path):
    s = make_stream(np.array([1, 2]), np.array([1, 2]), np.array([10, 2_000_000]),
                    np.array([1, 0]), 4, 4)
    write_events_npz(tmp_path / "us.npz", s)
    np.savez(tmp_path / "s.npz", x=s.x, y=s.y, t=s.t / 1e6, p=np.array([1, 0]))
    write_h5(tmp_path / "us.h5", s)
    (tmp_path / "s.txt").write_text("0.00001 1 1 1\n2.0 2 2 0\n")
    (tmp_path / "us.txt").write_text("10 1 1 1\n2000000 2 2 0\n")
    for name, unit in (("us.npz", "us"), ("s.npz", "s"), ("us.h5", "us"), ("s.txt", "s"),
                       ("us.txt", "us")):
        with open_events(tmp_path / name, ReadOptions(sensor=(4, 4))) as rec:
            assert rec.times_unit == unit, name
    with open_events(tmp_path / "us.npz", ReadOptions(time_unit="ms")) as rec:
        assert rec.times_unit == "ms"


def test_coordinates_outside_sensor(tmp_path):
    f = tmp_path / "e.txt"
    f.write_text("0.1 12 1 1\n")
    with pytest.raises(InputError, match="outside the sensor width 10"):
        open_events(f, ReadOptions(sensor=(10, 10)))


# ---------------------------------------------------------------- numpy
def test_npz_round_trip_with_windows(tmp_path, rng):
    s = random_stream(rng)
    wins = [Exposure(0, 40_000), Exposure(50_000, 90_000)]
    write_events_npz(tmp_path / "e.npz", s, wins)
    rec = open_events(tmp_path / "e.npz")
    _same(rec.events(), s)
    assert rec.stored_windows() == wins


@pytest.mark.parametrize("keys", [("xs", "ys", "ts", "ps"), ("x", "y", "timestamp", "polarity")])
def test_npz_key_variants_float_seconds(tmp_path, keys):
    np.savez(tmp_path / "e.npz", **dict(zip(keys, (np.array([1, 2]), np.array([0, 1]),
                                                  np.array([0.5, 1.25]), np.array([True, False])))))
    rec = open_events(tmp_path / "e.npz")
    assert rec.events().t.tolist() == [500_000, 1_250_000]
    assert rec.events().p.tolist() == [1, -1]
    assert rec.warnings  # size guessed


def test_npz_structured_and_npy(tmp_path, rng):
    s = random_stream(rng, n=100)
    np.savez(tmp_path / "e.npz", events=s.to_structured(), width=40, height=30)
    _same(open_events(tmp_path / "e.npz").events(), s)
    np.save(tmp_path / "e.npy", s.to_structured())
    _same(open_events(tmp_path / "e.npy", ReadOptions(sensor=(40, 30))).events(), s)
    cols = np.stack([s.t, s.x, s.y, s.p], 1)
    np.save(tmp_path / "c.npy", cols)
    _same(open_events(tmp_path / "c.npy", ReadOptions(sensor=(40, 30))).events(), s)


def test_npz_pickle_refused(tmp_path):
    np.savez(tmp_path / "e.npz", x=np.array([{"evil": 1}], dtype=object), y=np.zeros(1),
             t=np.zeros(1), p=np.zeros(1))
    with pytest.raises(FormatError, match="pickled"):
        open_events(tmp_path / "e.npz")


def test_npz_missing_keys_and_truncated(tmp_path, rng):
    np.savez(tmp_path / "e.npz", a=np.zeros(3))
    with pytest.raises(FormatError, match="no event arrays"):
        open_events(tmp_path / "e.npz")
    write_events_npz(tmp_path / "g.npz", random_stream(rng))
    data = (tmp_path / "g.npz").read_bytes()
    (tmp_path / "t.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError):
        open_events(tmp_path / "t.npz")


def test_pickle_file_is_not_text(tmp_path):
    (tmp_path / "e.npz").write_bytes(pickle.dumps({"x": [1]}))
    with pytest.raises(FormatError):
        open_events(tmp_path / "e.npz")


# ---------------------------------------------------------------- hdf5
def test_h5_round_trip_lazy_windows(tmp_path, rng, monkeypatch):
    import trmd_cli.read.hdf5 as h5mod

    monkeypatch.setattr(h5mod, "STRIDE", 7)  # exercise the coarse index with many blocks
    s = random_stream(rng, n=4000)
    blurry = rng.random((2, 30, 40)).astype(np.float32)
    sharp = rng.random((2, 7, 30, 40)).astype(np.float32)
    wins = [Exposure(0, 30_000), Exposure(50_000, 80_000)]
    write_h5(tmp_path / "e.h5", s, blurry=blurry, exposures=wins, sharp=sharp,
             contrast=[0.2, 0.3])
    with open_events(tmp_path / "e.h5") as rec:
        _same(rec.events(), s)
        for a, b in [(0, 1), (123, 45_678), (99_999, 200_000), (-5, 3)]:
            _same(rec.events(a, b), s.slice(a, b))
        assert rec.frame_exposures() == wins
        frames = list(rec.frames())
        np.testing.assert_array_equal(frames[1].image, blurry[1])
        np.testing.assert_array_equal(rec.ground_truth(1), sharp[1])
        assert rec.contrast(1) == pytest.approx(0.3)
        assert sum(len(c) for c in rec.iter_chunks(999)) == len(s)


def test_h5_frames_scale(tmp_path, rng):
    """Float frames are [0, 1] intensity, noise above 1 included (a bright frame with
    σ = 0.01 noise reaches ≈ 1.05: read as stored, not divided by 255); 8-bit counts, stored
    as integers or as floats, become [0, 1]."""
    s = random_stream(rng, n=200)
    wins = [Exposure(0, 30_000)] * 3
    noisy = np.clip(0.98 + rng.normal(0, 0.01, (30, 40)), 0.9, 1.06).astype(np.float32)
    counts = rng.integers(0, 256, (30, 40))
    write_h5(tmp_path / "f.h5", s, blurry=np.stack([noisy, counts.astype(np.float32),
                                                    counts.astype(np.float32)]),
             exposures=wins)
    with h5py.File(tmp_path / "f.h5", "r+") as f:
        del f["frames/blurry"]
        f["frames/blurry"] = np.stack([np.zeros((30, 40), np.uint8), counts.astype(np.uint8),
                                       np.zeros((30, 40), np.uint8)])
    with open_events(tmp_path / "f.h5") as rec:
        assert [f.image.max() for f in rec.frames()][:2] == [0.0, counts.max() / 255.0]
    write_h5(tmp_path / "g.h5", s, blurry=np.stack([noisy, counts.astype(np.float32), noisy]),
             exposures=wins)
    with open_events(tmp_path / "g.h5") as rec:
        got = [f.image for f in rec.frames()]
    assert noisy.max() > 1.02
    np.testing.assert_array_equal(got[0], noisy)
    np.testing.assert_allclose(got[1], counts / 255.0, rtol=1e-6)


def test_h5_event_utils_and_dsec_layouts(tmp_path):
    with h5py.File(tmp_path / "eu.h5", "w") as f:
        f.attrs["sensor_resolution"] = (180, 240)
        f["events/xs"] = np.array([1, 2], np.int16)
        f["events/ys"] = np.array([3, 4], np.int16)
        f["events/ts"] = np.array([0.25, 0.5])
        f["events/ps"] = np.array([1, 0], np.int8)
    rec = open_events(tmp_path / "eu.h5")
    assert rec.sensor_size() == (240, 180)
    assert rec.events().t.tolist() == [250_000, 500_000] and rec.events().p.tolist() == [1, -1]
    with h5py.File(tmp_path / "dsec.h5", "w") as f:
        f["events/x"] = np.array([1, 2], np.uint16)
        f["events/y"] = np.array([3, 4], np.uint16)
        f["events/t"] = np.array([10, 20], np.uint32)
        f["events/p"] = np.array([0, 1], np.uint8)
        f["t_offset"] = np.int64(1_000_000)
    s = open_events(tmp_path / "dsec.h5", ReadOptions(sensor=(640, 480))).events()
    assert s.t.tolist() == [1_000_010, 1_000_020] and s.p.tolist() == [-1, 1]


def test_h5_bad(tmp_path, rng):
    with h5py.File(tmp_path / "x.h5", "w") as f:
        f["stuff"] = np.zeros(3)
    with pytest.raises(FormatError, match="no 'events' group"):
        open_events(tmp_path / "x.h5")
    write_h5(tmp_path / "g.h5", random_stream(rng, n=100_000))
    data = (tmp_path / "g.h5").read_bytes()
    (tmp_path / "t.h5").write_bytes(data[: len(data) // 3])
    with pytest.raises(FormatError):
        rec = open_events(tmp_path / "t.h5")
        rec.events()
    with h5py.File(tmp_path / "u.h5", "w") as f:
        f.attrs.update(width=4, height=4)
        for k, v in dict(x=[0, 1], y=[0, 1], t=[5, 1], p=[1, 1]).items():
            f[f"events/{k}"] = np.array(v)
    with pytest.raises(InputError, match="not sorted"):
        open_events(tmp_path / "u.h5").events()


# ---------------------------------------------------------------- sniffing
def test_sniff_by_magic_not_extension(tmp_path, rng):
    write_events_npz(tmp_path / "e.npz", random_stream(rng))
    (tmp_path / "misnamed.txt").write_bytes((tmp_path / "e.npz").read_bytes())
    assert detect_format(tmp_path / "misnamed.txt") == "npz"
    (tmp_path / "empty.txt").write_bytes(b"")
    with pytest.raises(FormatError, match="empty"):
        detect_format(tmp_path / "empty.txt")
    (tmp_path / "noise.bin").write_bytes(bytes(range(256)) * 4)
    with pytest.raises(FormatError, match="unknown"):
        detect_format(tmp_path / "noise.bin")
    (tmp_path / "fake.h5").write_text("0.1 1 1 1\n")
    with pytest.raises(FormatError, match="not the content"):
        detect_format(tmp_path / "fake.h5")
    with pytest.raises(InputError, match="not found"):
        detect_format(tmp_path / "missing.npz")


def test_make_stream_never_mutates(rng):
    x, y, t, p = np.array([3, 1]), np.array([0, 0]), np.array([5, 1]), np.array([0, 1])
    copies = [a.copy() for a in (x, y, t, p)]
    s = make_stream(x, y, t, p, 4, 1, sort=True)
    assert s.t.tolist() == [1, 5] and s.x.tolist() == [1, 3]
    for a, c in zip((x, y, t, p), copies):
        np.testing.assert_array_equal(a, c)


# -- the time unit comes from the whole column ------------------------------------------------


def _esl_text(tmp_path, n=3000):
    """eSL-Net's layout: seconds normalised to the exposure, the first written as a bare 0."""
    rng = np.random.default_rng(3)
    t = np.sort(rng.random(n) * 0.1)
    t[0] = 0.0
    rows = ["0 10 20 1"] + [f"{ti:.11f} {rng.integers(0, 240)} {rng.integers(0, 180)} "
                            f"{rng.integers(0, 2)}" for ti in t[1:]]
    f = tmp_path / "events.txt"
    f.write_text("\n".join(rows) + "\n")
    return f, t


def test_fractional_times_after_an_integer_first_row_are_seconds(tmp_path):
    from trmd_cli.read import ReadOptions, open_events

    f, t = _esl_text(tmp_path)
    with open_events(f, ReadOptions(sensor=(240, 180))) as rec:
        s = rec.events()
        assert not any("distinct times" in w for w in rec.warnings)
    # every time to the microsecond, none truncated onto 0 or 1 µs
    np.testing.assert_array_equal(s.t, np.rint(t * 1e6).astype(np.int64))
    assert len(np.unique(s.t)) > 2000


def test_times_that_collapse_are_reported_with_the_unit_to_set(tmp_path):
    from trmd_cli.cli.app import app
    from trmd_cli.read import ReadOptions, open_events

    f, _ = _esl_text(tmp_path)
    # read as integer microseconds on purpose: 3000 events on a handful of instants
    with open_events(f, ReadOptions(sensor=(240, 180), time_unit="us")) as rec:
        assert len(np.unique(rec.events().t)) < 16
        line = next(w for w in rec.warnings if "distinct times" in w)
        assert "`time_unit`" in line
    r = CliRunner().invoke(app, ["info", str(f), "--sensor", "240x180", "--time-unit", "us"])
    assert r.exit_code == 0, r.output
    assert "distinct times" in r.stderr and "set --time-unit" in r.stderr
