"""The quick paths of the camera readers give exactly what the full decoding gives.

A .dat file larger than the in-memory cache is indexed on its raw records, and its chunks that
need no repair are unpacked without the checks the full decoding makes; windows asked in time
order are served by one sweep over the file; a span of many chunks is decoded into one set of
arrays. Each is checked against the events written and against the full decoder
(``decode_dat_records`` over the whole file at once), on files whose chunks hold every case a
chunk can be in: clean, a wrap of the 32-bit clock, a corrupt time, a long gap, an error.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.data import SHARED, assert_events, needs_shared
from tests.read.test_camera import write_dat
from trmd_cli.errors import FormatError
from trmd_cli.events import Exposure
from trmd_cli.read import ReadOptions, evt3_words, open_events, prophesee
from trmd_cli.read import chunked as chunked_mod
from trmd_cli.read.chunked import time_slice
from trmd_cli.read.prophesee import DatRecording, Evt3Recording, decode_dat_records

REC = SHARED / "recordings"


@pytest.fixture
def no_cache(monkeypatch):
    monkeypatch.setattr(chunked_mod, "CACHE_MAX_EVENTS", 0)


def _mixed_recording(rng, n=2942):
    """Events on a clock that wraps (2**32 µs) exactly between written records 319 and 320 (a
    chunk's edge for chunks of 64 and blocks of 5), jumps forward by 100 s at event 1500 and
    stays there; written with three corrupt times: a first record far before the rest, one at
    0xFFFFFFFF before event 2000, and three records ahead by more than half the counter that
    end the file (the whole last chunk of 64). Returns (written t, x, y, p, the true
    events)."""
    t = np.cumsum(rng.integers(1, 20_000, n)).astype(np.int64)
    t += (1 << 32) - (t[318] + t[319]) // 2  # written after one record more
    assert t[318] < 1 << 32 <= t[319]
    t[1500:] += 100_000_000  # a gap longer than CLOCK_JUMP_US that the clock keeps
    x, y = rng.integers(0, 64, n), rng.integers(0, 48, n)
    p = np.where(rng.integers(0, 2, n) == 1, 1, -1)
    true = (t, x, y, p)
    bad = 2000
    ahead = t[-1] + (1 << 31) + 1000 + np.arange(3)
    assert (ahead[-1] & 0xFFFFFFFF) > (t[-1] & 0xFFFFFFFF)  # ahead, not wrapped back
    wt = np.concatenate([[5], t[:bad], [0xFFFFFFFF], t[bad:], ahead])
    wx, wy, wp = (np.concatenate([[1], a[:bad], [2], a[bad:], [3, 3, 3]]) for a in (x, y, p))
    return wt, wx, wy, wp, true


def _full_decoding(path):
    """The reference: the full decoder on every record of the file at once."""
    data = path.read_bytes()
    off = prophesee.parse_header(data).data_offset + 2
    records = np.frombuffer(data[off:], prophesee._DAT_DTYPE)
    x, y, t, p, _ = decode_dat_records(records)
    return t, x, y, p


@pytest.mark.parametrize("block", [1 << 16, 5], ids=["block-per-chunk", "blocks-in-chunks"])
def test_dat_quick_paths_match_the_full_decoding(tmp_path, rng, monkeypatch, block):
    monkeypatch.setattr(prophesee, "DAT_BLOCK_EVENTS", block)
    wt, wx, wy, wp, (t, x, y, p) = _mixed_recording(rng)
    f = tmp_path / "mixed.dat"
    write_dat(f, wt, wx, wy, wp)
    ref = _full_decoding(f)
    for k, name in enumerate("txyp"):  # the reference itself decodes what was written
        np.testing.assert_array_equal(ref[k], (t, x, y, p)[k], err_msg=name)
    cached = DatRecording(f, ReadOptions(), chunk_events=64)
    assert cached._cache is not None
    monkeypatch.setattr(chunked_mod, "CACHE_MAX_EVENTS", 0)
    rec = DatRecording(f, ReadOptions(), chunk_events=64)
    assert rec._cache is None
    # the file exercises both kinds of chunk
    assert rec._clean.any() and not rec._clean.all()
    assert rec.warnings == cached.warnings
    note = next(w for w in rec.warnings if "corrupt record times" in w)
    assert note.startswith("5 corrupt record times (the first, record 0,")
    assert rec.num_events() == len(t) and rec.time_range_us() == (int(t[0]), int(t[-1]))
    assert_events(rec.events(), t, x, y, p)  # a span of many chunks: gathered
    assert_events(cached.events(), t, x, y, p)
    pieces = list(rec.iter_chunks(max_events=100))
    assert_events(type(pieces[0]).concatenate(pieces), t, x, y, p)
    lo, hi = int(t[700]), int(t[2200])  # starts and ends inside chunks
    m = (t >= lo) & (t < hi)
    assert_events(rec.events(lo, hi), t[m], x[m], y[m], p[m])
    assert_events(rec.events(lo + 0.5, hi - 0.5), *(a[(t >= lo + 1) & (t < hi)]
                                                   for a in (t, x, y, p)))


def test_dat_errors_are_the_same_on_both_paths(tmp_path, rng, monkeypatch):
    t = np.sort(rng.integers(1_000, 5_000_000, 1000)).astype(np.int64)
    x, y, p = rng.integers(0, 64, 1000), rng.integers(0, 48, 1000), np.ones(1000, int)
    cases = {}
    back = t.copy()
    back[700] = back[699] - 1  # a step back inside a chunk of 64 (event 700)
    cases["inside"] = (back, x, y, p, "event 700 goes back in time")
    edge = t.copy()
    edge[640] = edge[639] - 5  # the first record of chunk 10 is before the last of chunk 9
    cases["edge"] = (edge, x, y, p, "event 640 goes back in time")
    wide = x.copy()
    wide[900] = 70
    cases["x"] = (t, wide, y, p, "x coordinate 70 is outside the 64x48 sensor")
    for name, (tt, xx, yy, pp, message) in cases.items():
        f = tmp_path / f"{name}.dat"
        write_dat(f, tt, xx, yy, pp)
        for cache in (chunked_mod.CACHE_MAX_EVENTS, 0):
            monkeypatch.setattr(chunked_mod, "CACHE_MAX_EVENTS", cache)
            with pytest.raises(FormatError, match=message):
                DatRecording(f, ReadOptions(), chunk_events=64)
            monkeypatch.undo()
    f = tmp_path / "pol.dat"
    write_dat(f, t, x, y, p)
    data = bytearray(f.read_bytes())
    at = len(data) - 8 * (1000 - 800) + 7  # the top byte of record 800's address word
    data[at] = (data[at] & 0x0F) | 0x20  # polarity 2
    f.write_bytes(bytes(data))
    for cache in (chunked_mod.CACHE_MAX_EVENTS, 0):
        monkeypatch.setattr(chunked_mod, "CACHE_MAX_EVENTS", cache)
        with pytest.raises(FormatError, match="record 800 has polarity 2"):
            DatRecording(f, ReadOptions(), chunk_events=64)


def test_dat_without_a_size_guesses_it_alike_on_both_paths(tmp_path, rng, monkeypatch):
    t = np.sort(rng.integers(1_000, 5_000_000, 500))
    x, y = rng.integers(0, 50, 500), rng.integers(0, 30, 500)
    body = b"".join(int(ti).to_bytes(4, "little") + (int(xi) | int(yi) << 14).to_bytes(4,
                    "little") for ti, xi, yi in zip(t, x, y, strict=True))
    f = tmp_path / "nosize.dat"
    f.write_bytes(b"% Date 2024-01-01 00:00:00\n" + bytes([0x0C, 8]) + body)
    sizes = []
    for cache in (chunked_mod.CACHE_MAX_EVENTS, 0):
        monkeypatch.setattr(chunked_mod, "CACHE_MAX_EVENTS", cache)
        rec = DatRecording(f, ReadOptions(), chunk_events=64)
        sizes.append((rec.sensor_size(), rec.warnings))
    expected = (int(x.max()) + 1, int(y.max()) + 1)
    assert sizes[0] == sizes[1] and sizes[0][0] == expected
    assert "from the largest coordinates" in sizes[0][1][0]


def test_windows_in_time_order_are_swept_exactly(tmp_path, rng, no_cache):
    n = 4000
    t = np.sort(rng.integers(0, 2_000_000, n)).astype(np.int64)
    t[n // 2:] += 1_000_000  # a second without events between two chunks' spans
    x, y = rng.integers(0, 64, n), rng.integers(0, 48, n)
    p = np.where(rng.integers(0, 2, n) == 1, 1, -1)
    f = tmp_path / "w.dat"
    write_dat(f, t, x, y, p)
    rec = DatRecording(f, ReadOptions(), chunk_events=100)
    starts = np.sort(np.concatenate([rng.integers(-100_000, 3_200_000, 60),
                                     [2_100_000, 2_100_000, 2_500_000]]))  # some in the gap
    wins = []
    for s in starts:  # long and short windows mixed: the ends do not follow the starts' order
        d = int(rng.choice([1, 30, 5_000, 400_000, 1_500_000]))
        wins.append(Exposure(int(s), int(s) + d))
    wins.append(Exposure(3_500_000, 3_600_000))  # after the last event
    for margin in (0, 7):
        got = list(rec.iter_windows(wins, margin_us=margin))
        assert len(got) == len(wins)
        for w, ev in zip(wins, got, strict=True):
            m = (t >= w.start_us - margin) & (t <= w.end_us + margin)
            assert_events(ev, t[m], x[m], y[m], p[m])


def test_time_slice_matches_a_search_in_floats(rng):
    t = np.sort(rng.integers(-1000, 1000, 500)).astype(np.int64)
    bounds = [-np.inf, np.inf, np.nan, -2.0**70, 2.0**70, 1 << 80, -(1 << 80), 0, 0.0, -0.5]
    bounds += list(rng.uniform(-1100, 1100, 40)) + list(rng.integers(-1100, 1100, 40))
    bounds += [float(v) for v in t[::50]] + [v + 0.25 for v in t[::50]]
    for lo in bounds:
        for hi in bounds[::3]:
            want = np.searchsorted(t.astype(np.float64), [float(lo), float(hi)])
            s = time_slice(t, lo, hi)
            assert (s.start, s.stop) == tuple(want), (lo, hi)


def test_evt3_undefined_words_found_across_scan_blocks(tmp_path, monkeypatch):
    pytest.importorskip("evt3")
    import struct

    monkeypatch.setattr(evt3_words, "SCAN_WORDS", 3)
    words = [0x8000, 0x6010, 0x0005, 0x2803, 0x9123, 0xC000, 0x6020, 0x0007, 0x2004, 0xD001]
    f = tmp_path / "odd.raw"
    f.write_bytes(b"% evt 3.0\n% geometry 64x48\n% end\n" + struct.pack(f"<{len(words)}H",
                                                                        *words))
    with open_events(f) as rec:
        assert rec.events().t.tolist() == [16, 32]
        note = next(w for w in rec.warnings if "does not define" in w)
        assert note.startswith("3 word(s) of types 0x9, 0xC, 0xD") and "word 4)" in note


@needs_shared
def test_evt3_spans_of_many_batches_match_the_whole_file(no_cache):
    whole = Evt3Recording(REC / "evt3.raw", ReadOptions(), batch_bytes=1 << 30).events()
    rec = Evt3Recording(REC / "evt3.raw", ReadOptions(), batch_bytes=1 << 19)
    assert rec._cache is None and len(rec._count) > 10
    assert_events(rec.events(), whole.t, whole.x, whole.y, whole.p)
    lo, hi = int(whole.t[100_000]) + 0.5, int(whole.t[1_100_000])
    m = (whole.t >= lo) & (whole.t < hi)
    assert_events(rec.events(lo, hi), whole.t[m], whole.x[m], whole.y[m], whole.p[m])
    a, b = rec.time_range_us()
    wins = [Exposure(s, s + 49_999) for s in range(a, b + 1, 50_000)]
    assert sum(len(w) for w in rec.iter_windows(wins)) == len(whole)


@needs_shared
def test_gen4_dat_quick_path_matches_the_full_decoding(no_cache):
    rec = DatRecording(REC / "gen4.dat", ReadOptions(), chunk_events=1 << 17)
    assert rec._cache is None and rec._clean.all()
    ref = _full_decoding(REC / "gen4.dat")
    assert_events(rec.events(), *ref)
    assert rec.warnings == open_events(REC / "gen4.dat").warnings
