"""Camera-native readers: AEDAT4, Prophesee EVT 2.0 / EVT 3.0 / .dat, MATLAB .mat.

Shared recordings (../shared/data, skipped when absent) are checked against the counts in its
README and against expelliarmus as an independent decoder. Tiny files are written here byte by
byte from the public format descriptions and must round-trip exactly.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.data import SHARED, assert_events, needs_shared, random_events
from trmd_cli.errors import FormatError, InputError
from trmd_cli.events import Exposure, make_stream
from trmd_cli.read import ReadOptions, detect_format, open_events
from trmd_cli.read import chunked as chunked_mod
from trmd_cli.read.base import MemoryRecording
from trmd_cli.read.prophesee import DatRecording, Evt2Recording, Evt3Recording, parse_header

REC = SHARED / "recordings"
ESL = SHARED / "real" / "esl-cups"


# -- writers from the format descriptions -------------------------------------------------------


def write_evt2(path: Path, t, x, y, p, header: bytes = b"% evt 2.0\n% geometry 64x48\n",
               extra_words: dict[int, int] | None = None) -> None:
    """EVT 2.0: TIME_HIGH (0x8, time bits 33..6) whenever they change, then CD words
    (type 0 OFF / 1 ON, time bits 5..0 at 27..22, x at 21..11, y at 10..0). ``extra_words``
    inserts raw words before event i (triggers, OTHERS …)."""
    words = []
    high = None
    for i, (ti, xi, yi, pi) in enumerate(zip(t, x, y, p, strict=True)):
        for w in (extra_words or {}).get(i, []):
            words.append(w)
        if ti >> 6 != high:
            high = ti >> 6
            words.append((0x8 << 28) | (high & 0x0FFFFFFF))
        words.append(((1 if pi > 0 else 0) << 28) | ((ti & 0x3F) << 22) | (xi << 11) | yi)
    path.write_bytes(header + struct.pack(f"<{len(words)}I", *words))


def write_dat(path: Path, t, x, y, p, width=64, height=48, ev_type=0x0C, ev_size=8) -> None:
    """.dat: '%' header, event type and size bytes, then (uint32 t, uint32 x | y<<14 | p<<28)."""
    header = f"% Date 2024-01-01 00:00:00\n% Version 2\n% Width {width}\n% Height {height}\n"
    body = b"".join(struct.pack("<II", int(ti) & 0xFFFFFFFF,
                                int(xi) | (int(yi) << 14) | ((1 if pi > 0 else 0) << 28))
                    for ti, xi, yi, pi in zip(t, x, y, p, strict=True))
    path.write_bytes(header.encode() + bytes([ev_type, ev_size]) + body)


@pytest.fixture
def no_cache(monkeypatch):
    """Force the streaming paths: nothing kept in memory after indexing."""
    monkeypatch.setattr(chunked_mod, "CACHE_MAX_EVENTS", 0)


# -- EVT 2.0 ------------------------------------------------------------------------------------


def test_evt2_round_trip_exact(tmp_path, rng):
    t, x, y, p = random_events(rng)
    f = tmp_path / "a.raw"
    # a trigger (0xA) and an OTHERS word (0xE) mid-stream must be skipped
    write_evt2(f, t, x, y, p, extra_words={100: [0xA << 28 | 1], 2000: [0xE << 28 | 5]})
    assert detect_format(f) == "evt2"
    rec = open_events(f)
    assert rec.format == "evt2" and rec.sensor_size() == (64, 48) and rec.warnings == []
    assert rec.num_events() == len(t)
    assert rec.time_range_us() == (int(t[0]), int(t[-1]))
    assert_events(rec.events(), t, x, y, p)


def test_evt2_agrees_with_expelliarmus(tmp_path, rng):
    expelliarmus = pytest.importorskip("expelliarmus")
    t, x, y, p = random_events(rng, n=500)
    f = tmp_path / "b.raw"
    write_evt2(f, t, x, y, p)
    ref = expelliarmus.Wizard(encoding="EVT2", fpath=f).read()
    assert_events(open_events(f).events(), ref["t"], ref["x"], ref["y"],
                  np.where(ref["p"] == 1, 1, -1))


def test_evt2_chunks_and_windows_match_whole(tmp_path, rng, no_cache):
    t, x, y, p = random_events(rng, n=2000)
    f = tmp_path / "c.raw"
    write_evt2(f, t, x, y, p)
    rec = Evt2Recording(f, ReadOptions(), chunk_words=37)  # chunk edges inside everything
    assert rec._cache is None and len(rec._count) > 50
    assert_events(rec.events(), t, x, y, p)
    starts = np.sort(rng.integers(int(t[0]) - 1000, int(t[-1]), 25))
    durations = rng.integers(1, 400_000, 25)
    wins = [Exposure(int(s), int(s + d)) for s, d in zip(starts, durations, strict=True)]
    for w, got in zip(wins, rec.iter_windows(wins), strict=True):
        m = (t >= w.start_us) & (t <= w.end_us)  # closed window
        assert_events(got, t[m], x[m], y[m], p[m])
        half = rec.events(w.start_us, w.end_us)  # half-open [t0, t1)
        m = (t >= w.start_us) & (t < w.end_us)
        assert_events(half, t[m], x[m], y[m], p[m])
    assert sum(len(c) for c in rec.iter_chunks(max_events=300)) == len(t)


def test_evt2_time_high_wraps_after_34_bits(tmp_path):
    period = 1 << 34
    t = np.array([period - 200, period - 64, period + 5, period + 1000], np.int64)
    x, y, p = np.array([1, 2, 3, 4]), np.array([5, 6, 7, 8]), np.array([1, -1, 1, -1])
    f = tmp_path / "wrap.raw"
    write_evt2(f, t % period, x, y, p)  # the file can only hold 34 bits
    assert_events(open_events(f).events(), t, x, y, p)


def test_evt2_events_before_first_time_high_are_dropped_with_warning(tmp_path):
    f = tmp_path / "early.raw"
    cd_first = (1 << 28) | (3 << 22) | (1 << 11) | 2
    body = [cd_first, (0x8 << 28) | 10, (1 << 28) | (5 << 22) | (4 << 11) | 3]
    f.write_bytes(b"% evt 2.0\n% geometry 8x8\n" + struct.pack("<3I", *body))
    rec = open_events(f)
    assert_events(rec.events(), [10 * 64 + 5], [4], [3], [1])
    assert any("dropped" in w for w in rec.warnings)


def test_evt2_unknown_word_type_is_format_error(tmp_path, rng):
    t, x, y, p = random_events(rng, n=50)
    f = tmp_path / "bad.raw"
    write_evt2(f, t, x, y, p, extra_words={20: [0x5 << 28]})
    with pytest.raises(FormatError, match="type 0x5"):
        open_events(f)


def test_evt2_truncated_mid_word_is_format_error(tmp_path, rng):
    t, x, y, p = random_events(rng, n=50)
    f = tmp_path / "cut.raw"
    write_evt2(f, t, x, y, p)
    f.write_bytes(f.read_bytes()[:-2])
    with pytest.raises(FormatError, match="partial 32-bit word"):
        open_events(f)


def test_evt2_time_going_back_is_format_error(tmp_path):
    f = tmp_path / "back.raw"
    write_evt2(f, [5000, 9000, 100], [1, 2, 3], [1, 2, 3], [1, 1, 1])
    with pytest.raises(FormatError, match="back in time"):
        open_events(f)


def test_evt2_coordinates_outside_header_geometry_is_format_error(tmp_path):
    f = tmp_path / "big.raw"
    write_evt2(f, [10, 20], [3, 70], [1, 2], [1, 1])  # geometry 64x48
    with pytest.raises(FormatError, match="x coordinate 70"):
        open_events(f)


def test_evt2_sensor_size_rules(tmp_path):
    t, x, y, p = [10, 20], [3, 9], [1, 4], [1, -1]
    f = tmp_path / "s.raw"
    write_evt2(f, t, x, y, p, header=b"% evt 2.0\n% format EVT2;height=480;width=640\n")
    assert open_events(f).sensor_size() == (640, 480)
    write_evt2(f, t, x, y, p, header=b"% evt 2.0\n")
    rec = open_events(f)
    assert rec.sensor_size() == (10, 5) and any("`sensor" in w for w in rec.warnings)
    assert open_events(f, ReadOptions(sensor=(32, 16))).sensor_size() == (32, 16)
    write_evt2(f, t, x, y, p, header=b"% plugin_name hal_plugin_gen3_fx3\n")
    assert detect_format(f) == "evt2"  # Gen3 headers that do not name the encoding
    assert open_events(f).sensor_size() == (640, 480)


def test_header_parser_stops_at_binary_that_starts_with_percent():
    head = b"% evt 2.0\n% geometry 4x4\n%\x01\x02\x80\n\x00\x00"
    h = parse_header(head)
    assert h.data_offset == len(b"% evt 2.0\n% geometry 4x4\n")
    assert (h.width, h.height, h.encoding) == (4, 4, "evt2")


def test_sniff_prophesee_variants(tmp_path):
    f = tmp_path / "x.raw"
    f.write_bytes(b"% format EVT21;height=720;width=1280\n" + b"\x00" * 16)
    with pytest.raises(FormatError, match="EVT21"):
        detect_format(f)
    g = tmp_path / "table.txt"
    g.write_text("% t x y p\n10 1 2 1\n20 3 4 0\n")
    assert detect_format(g) == "text"
    h = tmp_path / "table.dat"
    h.write_text("% t x y p\n10 1 2 1\n20 3 4 0\n")
    assert detect_format(h) == "text"  # plain text tables also end in .dat


# -- .dat ---------------------------------------------------------------------------------------


def test_dat_round_trip_exact(tmp_path, rng):
    t, x, y, p = random_events(rng)
    f = tmp_path / "a.dat"
    write_dat(f, t, x, y, p)
    assert detect_format(f) == "dat"
    rec = open_events(f)
    assert rec.format == "dat" and rec.sensor_size() == (64, 48) and rec.warnings == []
    assert_events(rec.events(), t, x, y, p)


def test_dat_agrees_with_expelliarmus(tmp_path, rng):
    expelliarmus = pytest.importorskip("expelliarmus")
    t, x, y, p = random_events(rng, n=500)
    f = tmp_path / "b.dat"
    write_dat(f, t, x, y, p)
    ref = expelliarmus.Wizard(encoding="DAT", fpath=f).read()
    assert_events(open_events(f).events(), ref["t"], ref["x"], ref["y"],
                  np.where(ref["p"] == 1, 1, -1))


def test_dat_32bit_time_is_unwrapped_across_chunks(tmp_path, no_cache):
    t = np.array([2**32 - 30, 2**32 - 10, 2**32 + 3, 2**32 + 50, 2**32 + 2**31 + 100, 2**33 + 5],
                 np.int64)
    x, y, p = np.arange(6), np.arange(6) + 1, np.array([1, -1, 1, -1, 1, -1])
    f = tmp_path / "wrap.dat"
    write_dat(f, t, x, y, p)
    for chunk in (1, 2, 100):
        rec = DatRecording(f, ReadOptions(), chunk_events=chunk)
        assert_events(rec.events(), t, x, y, p)
        assert_events(rec.events(2**32, 2**32 + 51), t[2:4], x[2:4], y[2:4], p[2:4])


def test_dat_windows_from_chunks_match_whole(tmp_path, rng, no_cache):
    t, x, y, p = random_events(rng, n=3000)
    f = tmp_path / "w.dat"
    write_dat(f, t, x, y, p)
    rec = DatRecording(f, ReadOptions(), chunk_events=64)
    wins = [Exposure(int(a), int(a) + 150_000) for a in np.linspace(0, 5_000_000, 30)]
    for w, got in zip(wins, rec.iter_windows(wins, margin_us=1000), strict=True):
        m = (t >= w.start_us - 1000) & (t <= w.end_us + 1000)
        assert_events(got, t[m], x[m], y[m], p[m])


@pytest.mark.parametrize("damage, message", [
    (lambda b: b[:-3], "partial 8-byte event record"),
    (lambda b: b[: b.index(b"\x0c\x08")], "no event type"),
    (lambda b: b.replace(b"\x0c\x08", b"\x0c\x10", 1), "event size 16"),
    (lambda b: b.replace(b"\x0c\x08", b"\x03\x08", 1), "not CD events"),
])
def test_dat_damaged_is_format_error(tmp_path, damage, message):
    f = tmp_path / "d.dat"
    write_dat(f, [10, 20, 30], [1, 2, 3], [4, 5, 6], [1, -1, 1])
    f.write_bytes(damage(f.read_bytes()))
    with pytest.raises(FormatError, match=message):
        open_events(f)


def test_dat_bad_polarity_is_format_error(tmp_path):
    f = tmp_path / "p.dat"
    write_dat(f, [10, 20], [1, 2], [4, 5], [1, 1])
    raw = bytearray(f.read_bytes())
    raw[-1] |= 0x30  # polarity nibble 3
    f.write_bytes(bytes(raw))
    with pytest.raises(FormatError, match="polarity 3"):
        open_events(f)


# -- MATLAB -------------------------------------------------------------------------------------


def test_mat_esl_layout_round_trip(tmp_path, rng):
    sio = pytest.importorskip("scipy.io")
    t_us = 1_615_007_563_000_000 + np.sort(rng.integers(0, 104_000, 400))
    x, y = rng.integers(0, 346, 400), rng.integers(0, 260, 400)
    pol = rng.integers(0, 2, 400)
    f = tmp_path / "event000003.mat"
    sio.savemat(f, {"section_event_timestamp": (t_us / 1e6)[None], "section_event_x": x[None],
                    "section_event_y": y[None], "section_event_polarity": pol[None],
                    "start_timestamp": np.array([[1_615_007_563.0]]),
                    "end_timestamp": np.array([[1_615_007_563.104]])})
    assert detect_format(f) == "mat"
    rec = open_events(f, ReadOptions(sensor=(346, 260)))
    # epoch seconds in float64 resolve 0.24 µs: conversion must give the exact µs back
    assert_events(rec.events(), t_us, x, y, np.where(pol == 1, 1, -1))
    assert rec.stored_windows() == [Exposure(1_615_007_563_000_000, 1_615_007_563_104_000)]
    assert rec.warnings == []
    guessed = open_events(f)
    assert guessed.sensor_size() == (int(x.max()) + 1, int(y.max()) + 1)
    assert any("sensor size" in w for w in guessed.warnings)


def test_mat_plain_and_matrix_layouts(tmp_path):
    sio = pytest.importorskip("scipy.io")
    t = np.array([5, 17, 30], np.int64)
    x, y, p = np.array([1, 2, 3]), np.array([0, 1, 2]), np.array([-1, 1, 1])
    f = tmp_path / "plain.mat"
    sio.savemat(f, {"ts": t[:, None], "x": x[:, None], "y": y[:, None], "pol": p[:, None]})
    assert_events(open_events(f).events(), t, x, y, p)
    g = tmp_path / "matrix.mat"
    sio.savemat(g, {"events": np.stack([t / 1e6, x + 1, y + 1, (p > 0)], 1)})
    rec = open_events(g, ReadOptions(one_based=True))
    assert_events(rec.events(), t, x, y, p)
    ms = open_events(g, ReadOptions(one_based=True, time_unit="ms"))
    np.testing.assert_array_equal(ms.events().t, np.rint(t / 1e6 * 1e3).astype(np.int64))


def test_mat_v73_via_h5py(tmp_path):
    h5py = pytest.importorskip("h5py")
    f = tmp_path / "v73.mat"
    with h5py.File(f, "w", userblock_size=512) as h:
        for k, v in {"t": [[1.0, 2.5]], "x": [[1, 2]], "y": [[3, 4]], "p": [[1, 0]]}.items():
            h[k] = np.asarray(v).T  # MATLAB stores column-major: (1, N) lands as (N, 1)
    with open(f, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64".ljust(128, b" "))
    assert detect_format(f) == "mat"
    assert_events(open_events(f).events(), [1_000_000, 2_500_000], [1, 2], [3, 4], [1, -1])


def test_mat_errors(tmp_path):
    sio = pytest.importorskip("scipy.io")
    f = tmp_path / "other.mat"
    sio.savemat(f, {"foo": np.zeros(3), "bar": np.ones(2)})
    with pytest.raises(FormatError, match="bar, foo"):
        open_events(f)
    b = tmp_path / "bins.mat"
    sio.savemat(b, {"event_bins": np.zeros((2, 3, 4), np.int16)})
    with pytest.raises(FormatError, match="binned"):
        open_events(b)
    g = tmp_path / "ok.mat"
    sio.savemat(g, {"t": np.arange(1000.0), "x": np.zeros(1000), "y": np.zeros(1000),
                    "p": np.ones(1000)})
    cut = tmp_path / "cut.mat"
    cut.write_bytes(g.read_bytes()[:3000])
    with pytest.raises(FormatError):
        open_events(cut)
    bad = tmp_path / "nan.mat"
    sio.savemat(bad, {"t": np.array([0.0, np.nan]), "x": np.zeros(2), "y": np.zeros(2),
                      "p": np.ones(2)})
    with pytest.raises(InputError, match="non-finite"):
        open_events(bad)


def test_base_iter_windows_is_closed_interval():
    s = make_stream([0, 1, 2, 3], [0, 0, 0, 0], [10, 20, 30, 40], [1, 1, -1, -1], 4, 1)
    rec = MemoryRecording(s, Path("mem"), "npz")
    got = list(rec.iter_windows([Exposure(20, 30), Exposure(35, 40)], margin_us=0))
    assert [w.t.tolist() for w in got] == [[20, 30], [40]]


# -- shared recordings --------------------------------------------------------------------------


@needs_shared
def test_davis346_aedat4_events_and_frames():
    rec = open_events(REC / "davis346.aedat4")
    assert rec.format == "aedat4" and rec.sensor_size() == (346, 260)
    assert rec.num_events() == 78_830
    first, last = rec.time_range_us()
    assert abs((last - first) / 1e6 - 2.36) < 0.01
    ev = rec.events()
    assert set(np.unique(ev.p)) == {-1, 1} and (np.diff(ev.t) >= 0).all()
    exposures = rec.frame_exposures()
    assert len(exposures) == 59 and {e.duration_us for e in exposures} == {500}
    frames = list(rec.frames())
    assert len(frames) == 59
    f = frames[0]
    assert f.image.shape == (260, 346) and f.image.dtype == np.float32
    assert 0.0 <= f.image.min() and f.image.max() <= 1.0 and f.image.std() > 0.01
    assert [fr.exposure for fr in frames] == exposures
    # frames share the events' clock: the 25 Hz frames span the events' 2.36 s
    assert first - 40_000 < exposures[0].start_us and exposures[-1].end_us < last


@needs_shared
def test_davis346_aedat4_matches_raw_decoder(no_cache):
    aedat = pytest.importorskip("aedat")
    parts = [p["events"] for p in aedat.Decoder(str(REC / "davis346.aedat4")) if "events" in p]
    raw = np.concatenate(parts)
    rec = open_events(REC / "davis346.aedat4")
    assert rec._cache is None
    mid = int(raw["t"][len(raw) // 2])
    win = rec.events(mid, mid + 200_000)
    m = (raw["t"] >= mid) & (raw["t"] < mid + 200_000)
    assert_events(win, raw["t"][m].astype(np.int64), raw["x"][m], raw["y"][m],
                  np.where(raw["on"][m], 1, -1))
    exps = rec.frame_exposures()
    wide = [Exposure(e.start_us - 10_000, e.end_us + 10_000) for e in exps]
    for e, got in zip(wide, rec.iter_windows(wide), strict=True):
        m = (raw["t"] >= e.start_us) & (raw["t"] <= e.end_us)
        np.testing.assert_array_equal(got.t, raw["t"][m].astype(np.int64))


@needs_shared
@pytest.mark.parametrize("damage", ["truncate", "corrupt"])
def test_damaged_aedat4_is_format_error(tmp_path, damage):
    data = bytearray((REC / "davis346.aedat4").read_bytes())
    if damage == "truncate":
        data = data[: len(data) // 3]
    else:
        data[100_000:100_100] = b"\xff" * 100
    f = tmp_path / "bad.aedat4"
    f.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="truncated or corrupt"):
        open_events(f)


@needs_shared
def test_evt3_raw_counts():
    rec = open_events(REC / "evt3.raw")
    assert rec.format == "evt3" and rec.sensor_size() == (1280, 720)
    assert rec.num_events() == 1_218_618
    first, last = rec.time_range_us()
    assert abs((last - first) / 1e6 - 10.77) < 0.01
    assert list(rec.frames()) == []


@needs_shared
def test_evt3_streaming_matches_whole(no_cache):
    whole = open_events(REC / "evt3.raw").events()
    assert len(whole) == 1_218_618
    rec = Evt3Recording(REC / "evt3.raw", ReadOptions(), batch_bytes=1 << 20)
    assert rec._cache is None and len(rec._count) > 5
    t0 = int(whole.t[0])
    wins = [Exposure(t0 + k * 1_000_000, t0 + k * 1_000_000 + 30_000) for k in range(0, 10, 3)]
    for w, got in zip(wins, rec.iter_windows(wins), strict=True):
        i0, i1 = np.searchsorted(whole.t, [w.start_us, w.end_us + 1])
        assert_events(got, whole.t[i0:i1], whole.x[i0:i1], whole.y[i0:i1], whole.p[i0:i1])


@needs_shared
def test_gen4_dat_is_the_evt3_recording():
    dat = open_events(REC / "gen4.dat").events()
    evt3 = open_events(REC / "evt3.raw").events()
    assert len(dat) == len(evt3) == 1_218_618
    np.testing.assert_array_equal(dat.x, evt3.x)
    np.testing.assert_array_equal(dat.y, evt3.y)
    np.testing.assert_array_equal(dat.p, evt3.p)
    # the .dat export starts its clock later: one constant offset, nothing else
    offset = evt3.t - dat.t
    assert offset.min() == offset.max() > 0


@needs_shared
@pytest.mark.parametrize("name, encoding", [("evt2.raw", "EVT2"), ("gen4.dat", "DAT")])
def test_prophesee_numpy_decoders_match_expelliarmus(name, encoding):
    expelliarmus = pytest.importorskip("expelliarmus")
    ref = expelliarmus.Wizard(encoding=encoding, fpath=REC / name).read()
    rec = open_events(REC / name)
    assert_events(rec.events(), ref["t"], ref["x"], ref["y"], np.where(ref["p"] == 1, 1, -1))


@needs_shared
def test_evt2_raw_counts():
    rec = open_events(REC / "evt2.raw")
    assert rec.format == "evt2" and rec.num_events() == 521_252
    assert rec.sensor_size() == (640, 480)  # Gen3 plugin named in the header
    first, last = rec.time_range_us()
    assert abs((last - first) / 1e6 - 0.096) < 0.001


@needs_shared
def test_esl_cups_mat_files():
    sio = pytest.importorskip("scipy.io")
    files = sorted((ESL / "mat").glob("event*.mat"))
    assert len(files) == 8
    for f in files[:3]:
        raw = sio.loadmat(f)
        rec = open_events(f, ReadOptions(sensor=(346, 260)))
        assert 35_000 <= rec.num_events() <= 126_000
        assert rec.num_events() == raw["section_event_x"].size
        (win,) = rec.stored_windows()
        assert abs(win.duration_us - 104_000) <= 2
        ev = rec.events()
        np.testing.assert_array_equal(ev.p, np.where(raw["section_event_polarity"].ravel() == 1,
                                                     1, -1))
        assert np.abs(ev.t - raw["section_event_timestamp"].ravel() * 1e6).max() <= 1.0
        # each file holds exactly its frame's exposure
        assert win.start_us <= ev.t[0] and ev.t[-1] <= win.end_us


SHARED_FILES = ["recordings/davis346.aedat4", "recordings/evt3.raw", "recordings/gen4.dat",
                "recordings/evt2.raw", "real/esl-cups/mat/event000014.mat",
                "real/esl-cups/mat/event000021.mat"]


def _cli():
    pytest.importorskip("trmd_cli.cli.info")
    pytest.importorskip("trmd_cli.cli.voxelize")
    from trmd_cli.cli.app import app

    return app


@needs_shared
@pytest.mark.parametrize("rel", SHARED_FILES)
def test_cli_info_on_shared_file(rel):
    import json

    app = _cli()
    r = CliRunner().invoke(app, ["info", str(SHARED / rel), "--json"])
    assert r.exit_code == 0, r.output
    info = json.loads(r.stdout)
    expected = {"davis346.aedat4": 78_830, "evt3.raw": 1_218_618, "gen4.dat": 1_218_618,
                "evt2.raw": 521_252}
    name = Path(rel).name
    if name in expected:
        assert info["events"] == expected[name]
    if name == "davis346.aedat4":
        assert len(info["frames"]) == 59


@needs_shared
@pytest.mark.parametrize("rel", SHARED_FILES)
def test_cli_voxelize_on_shared_file(rel, tmp_path):
    app = _cli()
    out = tmp_path / "vox.npz"
    args = ["voxelize", str(SHARED / rel), "-o", str(out), "--n", "2"]
    if rel.endswith(".mat"):
        args += ["--sensor", "346x260"]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    with np.load(out) as z:
        vox, exposure = z["voxels"], z["exposure"]
    rec = open_events(SHARED / rel, ReadOptions(sensor=(346, 260)) if rel.endswith(".mat")
                      else ReadOptions())
    windows = 59 if rel.endswith("aedat4") else 1
    assert vox.shape == (windows, 4, rec.height, rec.width)
    # every event of a window lands in the voxels: |V(0)| + |V(2N)| sums the halves' counts
    w = Exposure(int(exposure[0, 0]), int(exposure[0, 1]))
    ev = rec.events(w.start_us, w.end_us + 1)
    assert np.abs(vox[0]).sum() > 0 or len(ev) == 0
    np.testing.assert_allclose(vox[0, 0].sum() * -1 + vox[0, -1].sum(), ev.p.sum(), atol=0.5)


def test_unsorted_windows_fall_back_to_random_access(tmp_path, rng, no_cache):
    t, x, y, p = random_events(rng, n=1000)
    f = tmp_path / "u.dat"
    write_dat(f, t, x, y, p)
    rec = DatRecording(f, ReadOptions(), chunk_events=50)
    wins = [Exposure(3_000_000, 3_100_000), Exposure(100_000, 900_000), Exposure(2_000, 2_001)]
    for w, got in zip(wins, rec.iter_windows(wins), strict=True):
        m = (t >= w.start_us) & (t <= w.end_us)
        np.testing.assert_array_equal(got.t, t[m])


class _ListRecording(chunked_mod.ChunkedRecording):
    """Chunks from a list; counts decoded chunks. Non-seekable ones decode from the start."""

    def __init__(self, parts, seekable: bool):
        super().__init__(Path("list"), "list", 64, 48)
        self.parts, self.seekable, self.decoded = parts, seekable, 0
        self._build_index()

    def _decode(self, start=0, resume=None):
        first = start if self.seekable and resume is not None else 0
        for i in range(first, len(self.parts)):
            self.decoded += 1
            if i >= start:
                yield chunked_mod.Chunk(i, *self.parts[i], resume=i if self.seekable else None)


@pytest.mark.parametrize("seekable", [True, False])
def test_chunk_cursor_random_and_sequential_requests(rng, no_cache, seekable):
    t, x, y, p = random_events(rng, n=3000)
    cuts = np.sort(rng.choice(np.arange(1, len(t)), 60, replace=False))
    cuts = np.concatenate([[0], cuts, cuts[10:13], [len(t)]])  # repeated cuts: empty chunks
    cuts.sort()
    parts = [(x[a:b].astype(np.uint16), y[a:b].astype(np.uint16), t[a:b], p[a:b].astype(np.int8))
             for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
    rec = _ListRecording(parts, seekable)
    assert rec._cache is None and rec.num_events() == len(t)
    for _ in range(300):  # any order, overlapping, nested, empty, outside
        lo = int(rng.integers(-10_000, 5_100_000))
        hi = lo + int(rng.choice([0, 1, 50, 5_000, 300_000, 3_000_000]))
        m = (t >= lo) & (t < hi)
        assert_events(rec.events(lo, hi), t[m], x[m], y[m], p[m])
    rec.close()
    rec.decoded = 0
    wins = [Exposure(s, s + 79_999) for s in range(0, 5_100_000, 80_000)]
    total = 0
    for w, got in zip(wins, rec.iter_windows(wins), strict=True):
        m = (t >= w.start_us) & (t <= w.end_us)
        assert_events(got, t[m], x[m], y[m], p[m])
        total += len(got)
    assert total == len(t)
    # windows in time order cost one pass: every chunk decoded once
    assert rec.decoded <= len(parts)


def test_evt3_body_without_events_or_time_words_is_an_error(tmp_path):
    """Two stray bytes after an EVT 3.0 header are not an empty recording; a body of only
    TIME_HIGH words (a camera that saw nothing) is."""
    import struct

    pytest.importorskip("evt3")
    head = b"% evt 3.0\n% geometry 64x48\n% end\n"
    bad = tmp_path / "stray.raw"
    bad.write_bytes(head + b"\x01\x02")
    with pytest.raises(FormatError, match="promises EVT 3.0 .* no event and no time word"):
        open_events(bad)
    quiet = tmp_path / "quiet.raw"
    quiet.write_bytes(head + struct.pack("<2H", 0x8001, 0x8002))
    with open_events(quiet) as rec:
        assert rec.num_events() == 0
