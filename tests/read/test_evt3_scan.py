"""EVT 3.0 files opened on a scan of their words and decoded once, as they are read.

The files here are written word by word from known events (times, rows, columns, vectors), on
a clock that wraps its 24 bits several times, with the segments of the scan made small so that
decoders start at many points inside vectors and rows. Every read is checked against the
events written and against the ``evt3`` decoder run over the whole file.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from tests.helpers.data import SHARED, assert_events, needs_shared
from trmd_cli import threads
from trmd_cli.errors import FormatError
from trmd_cli.events import Exposure
from trmd_cli.read import ReadOptions, evt3_words, prophesee
from trmd_cli.read import chunked as chunked_mod
from trmd_cli.read.prophesee import Evt3Recording

evt3 = pytest.importorskip("evt3")

HEAD = b"% evt 3.0\n% format EVT3;height=48;width=64\n% end\n"
W, H = 64, 48


@pytest.fixture(autouse=True)
def no_cache(monkeypatch):
    monkeypatch.setattr(chunked_mod, "CACHE_MAX_EVENTS", 0)


def _word(kind: int, value: int) -> int:
    return (kind << 12) | value


def write_evt3(path, rng, groups=3000, repeat_time=2, wide_steps=False):
    """Events in groups at increasing times: a single ADDR_X, or a VECT_BASE_X with a run of
    VECT_12/VECT_8; rows change now and then (a row set once serves many groups). TIME_HIGH
    is written at each change of its 12 bits (``repeat_time`` times, as cameras repeat it),
    every step included. Returns the path and the events (t, x, y, p) in file order."""
    words: list[int] = []
    xs, ys, ps, ts = [], [], [], []
    t, high, y, prev_t_high = 0, -1, None, 0
    step = (20_000, 400_000) if wide_steps else (1, 3_000)
    for _ in range(groups):
        t += int(rng.integers(*step))
        h = (t >> 12) & 0xFFF
        # every step of the high bits gets its word (a camera sends one each 4096 µs)
        walk = [h] if high < 0 else [(high + k) & 0xFFF for k in
                                     range(1, ((t >> 12) - prev_t_high) + 1)]
        for v in walk:
            words.extend([_word(0x8, v)] * repeat_time)
        high, prev_t_high = h, t >> 12
        words.append(_word(0x6, t & 0xFFF))
        if y is None or rng.random() < 0.3:
            y = int(rng.integers(0, H))
            words.append(_word(0x0, y))
        pol = int(rng.integers(0, 2))
        if rng.random() < 0.4:
            x = int(rng.integers(0, W))
            words.append(_word(0x2, x | pol << 11))
            xs.append(x), ys.append(y), ps.append(pol), ts.append(t)
            continue
        base = int(rng.integers(0, 8))
        words.append(_word(0x3, base | pol << 11))
        while base < W - 12:
            if rng.random() < 0.5:
                width, kind = 12, 0x4
            else:
                width, kind = 8, 0x5
            mask = int(rng.integers(0, 1 << width))
            words.append(_word(kind, mask))
            for b in range(width):
                if mask >> b & 1:
                    xs.append(base + b), ys.append(y), ps.append(pol), ts.append(t)
            base += width
            if rng.random() < 0.3:
                break
    path.write_bytes(HEAD + np.asarray(words, "<u2").tobytes())
    order = np.argsort(np.asarray(ts), kind="stable")  # (already in order: times increase)
    assert (np.diff(order) == 1).all()
    return path, (np.asarray(ts, np.int64), np.asarray(xs), np.asarray(ys),
                  np.where(np.asarray(ps) > 0, 1, -1))


def _lazy(path, monkeypatch, block=512):
    monkeypatch.setattr(evt3_words, "SCAN_WORDS", block)
    rec = Evt3Recording(path, ReadOptions(), eager_bytes=0)
    assert rec._scan is not None and len(rec._ordinal) > 20
    return rec


def test_scan_wraps_follow_the_decoder():
    # the decoder's rule, measured: a drop of 4085 or more between time words is a wrap
    def second_time(a, b):
        words = [_word(0x8, a), _word(0x0, 1), _word(0x2, 1), _word(0x8, b), _word(0x2, 2)]
        ev = evt3.Decoder(64, 48).feed(np.asarray(words, "<u2").tobytes())
        return int(np.asarray(ev.t)[1])

    for a, b in [(4095, 0), (4095, 10), (4095, 11), (4085, 0), (4084, 0), (2048, 0)]:
        wraps = a - b >= evt3_words.WRAP_MIN_DROP
        assert second_time(a, b) == (int(wraps) << 24) + (b << 12), (a, b)


def test_lazy_reads_equal_the_written_events(tmp_path, monkeypatch):
    rng = np.random.default_rng(3)
    path, (t, x, y, p) = write_evt3(tmp_path / "w.raw", rng, groups=2500, wide_steps=True)
    assert t[-1] > 3 << 24  # the 24-bit clock wraps at least three times
    whole = evt3.decode_file(str(path))
    np.testing.assert_array_equal(np.asarray(whole.t), t)
    rec = _lazy(path, monkeypatch)
    assert rec._scan.wraps[-1] >= 3
    assert rec.time_range_us() == (int(t[0]), int(t[-1]))
    assert not rec.is_empty() and rec.num_events() == len(t)
    assert_events(rec.events(), t, x, y, p)
    # windows anywhere, each decoded from the nearest start point (row and vector column given)
    for lo, hi in [(t[10], t[11]), (t[500] + 1, t[900]), (t[-40], t[-1] + 1), (0, t[3]),
                   (t[1200], t[1200] + 1)]:
        m = (t >= lo) & (t < hi)
        assert_events(rec.events(lo, hi), t[m], x[m], y[m], p[m])
    # one sweep over windows in time order: every event once
    edges = np.linspace(t[0], t[-1] + 1, 37).astype(np.int64)
    wins = [Exposure(int(a), int(b) - 1) for a, b in zip(edges[:-1], edges[1:], strict=True)]
    got = list(rec.iter_windows(wins))
    assert sum(len(g) for g in got) == len(t)
    for g, w in zip(got, wins, strict=True):
        m = (t >= w.start_us) & (t <= w.end_us)
        assert_events(g, t[m], x[m], y[m], p[m])


def test_whole_file_first_does_not_wait_for_the_index(tmp_path, monkeypatch):
    # the scan runs beside the first read; the whole file read first decodes meanwhile and
    # gives what the decoder gives, and the index is right once it is there
    rng = np.random.default_rng(8)
    path, (t, x, y, p) = write_evt3(tmp_path / "f.raw", rng, groups=2500, wide_steps=True)
    monkeypatch.setattr(evt3_words, "SCAN_WORDS", 512)
    decoding = threading.Event()
    decode, scan = evt3.decode_file, prophesee.scan_evt3

    def watched_decode(*args, **kwargs):
        decoding.set()
        return decode(*args, **kwargs)

    def slow_scan(*args):
        # finishes only once the decoder has started: a read that waited for the index
        # first would leave this to time out
        assert decoding.wait(10), "the whole file's read waited for the scan"
        return scan(*args)

    monkeypatch.setattr(evt3, "decode_file", watched_decode)
    monkeypatch.setattr(prophesee, "scan_evt3", slow_scan)
    monkeypatch.setattr(threads, "product_threads", lambda: 2)
    rec = Evt3Recording(path, ReadOptions(), eager_bytes=0)
    assert_events(rec.events(), t, x, y, p)
    assert len(rec._ordinal) > 20
    assert rec.time_range_us() == (int(t[0]), int(t[-1]))
    assert rec.warnings == []


def test_large_body_without_time_words_is_refused_when_read(tmp_path):
    import struct

    head = b"% evt 3.0\n% geometry 64x48\n% end\n"
    bad = tmp_path / "stray.raw"
    bad.write_bytes(head + struct.pack("<4H", 0x0001, 0x2002, 0x0003, 0x2004))
    rec = Evt3Recording(bad, ReadOptions(), eager_bytes=0)
    with pytest.raises(FormatError, match="promises EVT 3.0 .* no event and no time word"):
        rec.events()


def test_every_start_point_resumes_exactly(tmp_path, monkeypatch):
    rng = np.random.default_rng(4)
    path, (t, x, y, p) = write_evt3(tmp_path / "r.raw", rng, groups=1500)
    rec = _lazy(path, monkeypatch, block=256)
    seen = 0
    for k in range(len(rec._ordinal)):
        ch = rec._one_chunk(k)
        n = len(ch.t)
        assert_events(rec._join([ch]), t[seen:seen + n], x[seen:seen + n], y[seen:seen + n],
                      p[seen:seen + n])
        lo, hi = rec._first[k], rec._last[k]
        assert n == 0 or (lo <= ch.t[0] and ch.t[-1] <= hi)
        seen += n
    assert seen == len(t)


def test_scan_keeps_only_defined_words_and_finds_bad_ones(tmp_path, monkeypatch):
    rng = np.random.default_rng(5)
    path, (t, *_) = write_evt3(tmp_path / "u.raw", rng, groups=400)
    body = bytearray(path.read_bytes()[len(HEAD):])
    body[2 * 701: 2 * 702] = np.asarray([0x9ABC], "<u2").tobytes()
    path.write_bytes(HEAD + bytes(body))
    rec = _lazy(path, monkeypatch, block=64)
    note = next(w for w in rec.warnings if "does not define" in w)
    assert note.startswith("1 word(s) of type 0x9") and "word 701)" in note


def _clock_back(tmp_path, steps):
    """A recording whose TIME_HIGH words, from the middle on, are ``steps`` behind."""
    rng = np.random.default_rng(6)
    path, _ = write_evt3(tmp_path / f"b{steps}.raw", rng, groups=800)
    words = np.frombuffer(path.read_bytes()[len(HEAD):], "<u2").copy()
    times = np.flatnonzero(words >> 12 == 0x8)
    later = times[len(times) // 2:]
    assert (words[later] & 0xFFF).min() >= steps  # no wrap in this one
    words[later] -= steps
    path.write_bytes(HEAD + words.tobytes())
    return path


def test_clock_going_back_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(evt3_words, "SCAN_WORDS", 512)
    # far back: the segments' time bounds go back, seen by the scan started on opening, as
    # soon as anything is read (the whole file too, which does not wait for the index)
    far = _clock_back(tmp_path, 100)
    for read in (lambda r: r.time_range_us(), lambda r: r.events(), lambda r: r.warnings):
        rec = Evt3Recording(far, ReadOptions(), eager_bytes=0)
        with pytest.raises(FormatError, match="clock goes back in time near word"):
            read(rec)
        with pytest.raises(FormatError, match="clock goes back in time near word"):
            rec.num_events()  # and again on the next request
    # a little: the events' times go back, seen when they are decoded
    with pytest.raises(FormatError, match="goes back in time"):
        Evt3Recording(_clock_back(tmp_path, 2), ReadOptions(), eager_bytes=0).events()


def test_bad_coordinates_are_refused_when_read(tmp_path, monkeypatch):
    rng = np.random.default_rng(7)
    path, (t, *_) = write_evt3(tmp_path / "c.raw", rng, groups=800)
    words = np.frombuffer(path.read_bytes()[len(HEAD):], "<u2").copy()
    singles = np.flatnonzero(words >> 12 == 0x2)
    words[singles[-3]] = _word(0x2, 1000)  # column 1000 on a 64-wide sensor
    path.write_bytes(HEAD + words.tobytes())
    rec = _lazy(path, monkeypatch, block=128)
    assert rec.events(t[0], t[5]) is not None  # the start of the file is fine
    with pytest.raises(FormatError, match="x coordinate 1000 is outside the 64x48 sensor"):
        rec.events()


@needs_shared
def test_shared_recording_lazy_equals_eager(monkeypatch):
    path = SHARED / "recordings" / "evt3.raw"
    eager = Evt3Recording(path, ReadOptions())
    assert eager._scan is None
    whole = eager.events()
    rec = Evt3Recording(path, ReadOptions(), eager_bytes=0)
    assert rec._scan is not None
    assert rec.time_range_us() == eager.time_range_us()
    assert rec.num_events() == len(whole) == 1_218_618
    assert rec.warnings == eager.warnings
    assert_events(rec.events(), whole.t, whole.x, whole.y, whole.p)
    rng = np.random.default_rng(0)
    a, b = rec.time_range_us()
    for _ in range(12):
        lo = int(rng.integers(a, b))
        hi = lo + int(rng.integers(1, 3_000_000))
        m = (whole.t >= lo) & (whole.t < hi)
        assert_events(rec.events(lo, hi), whole.t[m], whole.x[m], whole.y[m], whole.p[m])
    wins = [Exposure(s, s + 49_999) for s in range(a, b + 1, 50_000)]
    assert sum(len(w) for w in rec.iter_windows(wins)) == len(whole)
