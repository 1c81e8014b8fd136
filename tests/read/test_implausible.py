"""Values that cannot be true: said, skipped where the format allows it, or refused — never
taken silently.

A damaged EVT 2.0 TIME_HIGH word or .dat time is a jump of the clock that the next time words
undo (not a wrap that shifts the rest of the file by hours); a header declaring a sensor no
camera has is refused by its line; text lines with a time of ``nan`` or a field too many, arrays
of another shape, EVT 3.0 words of no defined type, frames outside [0, 1] or holding ±inf are
said or refused. Files are written byte by byte from the format descriptions.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from tests.read.test_camera import assert_events, write_dat, write_evt2
from trmd_cli.cli.app import app
from trmd_cli.errors import FormatError, InputError
from trmd_cli.read import ReadOptions, open_events
from trmd_cli.read.prophesee import DatRecording, Evt2Recording

runner = CliRunner()


def events_3ms(n: int = 60, seed: int = 0):
    """A 3 ms recording (t = 1000 … 3999 µs) on a 64x48 sensor."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(1000, 4000, n)).astype(np.int64)
    return t, rng.integers(0, 64, n), rng.integers(0, 48, n), np.where(rng.random(n) < .5, 1, -1)


# -- a clock that jumps and comes back -----------------------------------------------------------


@pytest.mark.parametrize("chunk", [1 << 20, 7], ids=["one-chunk", "chunk-edges"])
def test_evt2_corrupt_time_high_is_skipped_not_a_wrap(tmp_path, chunk):
    t, x, y, p = events_3ms()
    # the corrupt word lands between two events of one time-high: the events after it, up to
    # the next real time-high word, have no trustworthy time
    i = next(k for k in range(20, 60) if t[k] >> 6 == t[k - 1] >> 6)
    f = tmp_path / "damaged.raw"
    write_evt2(f, t, x, y, p, extra_words={i: [(0x8 << 28) | 0x0FFFFFFF]})
    timed = [k for k in range(i, len(t)) if t[k] >> 6 == t[i] >> 6]
    keep = np.setdiff1d(np.arange(len(t)), timed)
    rec = Evt2Recording(f, ReadOptions(), chunk_words=chunk)
    s = rec.events()
    assert_events(s, t[keep], x[keep], y[keep], p[keep])
    assert rec.time_range_us()[1] < 4000  # was 17,179 s: the next word counted as a wrap
    note = next(w for w in rec.warnings if "corrupt TIME_HIGH" in w)
    assert f"{len(timed)} event(s)" in note and "17179.869" in note and "not taken for a " \
        "clock wrap" in note


def test_evt2_corrupt_first_time_high_is_skipped(tmp_path):
    t, x, y, p = events_3ms()
    f = tmp_path / "damaged.raw"
    # the very first word is a corrupt time-high: the real one follows before any event
    write_evt2(f, t, x, y, p, extra_words={0: [(0x8 << 28) | 0x0ABCDEF]})
    rec = open_events(f)
    assert_events(rec.events(), t, x, y, p)
    assert any("corrupt TIME_HIGH" in w for w in rec.warnings)


@pytest.mark.parametrize("where", ["middle", "last"])
def test_dat_record_at_0xffffffff_is_skipped_not_a_wrap(tmp_path, where):
    t, x, y, p = events_3ms()
    i = 30 if where == "middle" else len(t)
    bad_t = np.insert(t, i, 0xFFFFFFFF)
    f = tmp_path / "damaged.dat"
    write_dat(f, bad_t, np.insert(x, i, 1), np.insert(y, i, 1), np.insert(p, i, 1))
    for chunk in (1 << 20, 4):
        rec = DatRecording(f, ReadOptions(), chunk_events=chunk)
        assert_events(rec.events(), t, x, y, p)  # was: 4,295 s from record i on
        note = next(w for w in rec.warnings if "corrupt record time" in w)
        assert f"record {i}" in note and "4294.967295 s" in note


def test_a_real_gap_and_a_real_wrap_are_kept(tmp_path):
    """A clock that jumps and stays (a quiet stretch of minutes, the 32-bit wrap) is data."""
    t = np.array([1000, 2000, 2_000_000_000, 2_000_001_000, 4_000_000_000, 2**32 + 5],
                 np.int64)
    f = tmp_path / "gap.dat"
    write_dat(f, t, np.arange(6), np.arange(6), np.ones(6))
    rec = open_events(f)
    np.testing.assert_array_equal(rec.events().t, t)
    assert not any("corrupt" in w for w in rec.warnings)


# -- sensor sizes no camera has ---------------------------------------------------------------


@pytest.mark.parametrize("fmt,line", [("raw", "% geometry 99999x99999"),
                                      ("raw", "% format EVT2;height=720;width=99999"),
                                      ("dat", "% Width 999999")])
def test_header_sensor_beyond_any_camera_is_refused_by_its_line(tmp_path, fmt, line):
    t, x, y, p = events_3ms()
    f = tmp_path / f"big.{fmt}"
    if fmt == "raw":
        write_evt2(f, t, x, y, p, header=f"% evt 2.0\n{line}\n".encode())
    else:
        write_dat(f, t, x, y, p, width=999999)
    with pytest.raises(FormatError, match="no event camera is larger than 8192x8192") as e:
        open_events(f)
    assert line.split()[1] in str(e.value) and "`sensor=(W, H)`" in str(e.value)
    r = runner.invoke(app, ["info", str(f)])
    assert r.exit_code == 2 and "--sensor WxH" in r.stderr, r.output
    with open_events(f, ReadOptions(sensor=(64, 48))) as rec:  # the way out the hint gives
        assert rec.sensor_size() == (64, 48)
        assert any("which no camera has" in w for w in rec.warnings)


def test_the_memory_message_names_options_of_the_command():
    from trmd_cli.cli.boundary import _LESS_MEMORY

    assert "--set data.batch_size" in _LESS_MEMORY["train"]
    for command in ("voxelize", "deblur", "hfr", ""):
        assert "--set" not in _LESS_MEMORY[command], command


# -- EVT 3.0 words of no defined type ----------------------------------------------------------


def test_evt3_words_of_undefined_types_are_said(tmp_path):
    pytest.importorskip("evt3")
    words = [0x8000, 0x6010, 0x0005, 0x2803,  # TIME_HIGH 0, TIME_LOW 16, y = 5, ON at x = 3
             0x9123, 0xC000,  # two words of types EVT 3.0 does not define
             0x6020, 0x0007, 0x2004]  # TIME_LOW 32, y = 7, OFF at x = 4
    f = tmp_path / "odd.raw"
    f.write_bytes(b"% evt 3.0\n% geometry 64x48\n% end\n" + struct.pack(f"<{len(words)}H",
                                                                        *words))
    with open_events(f) as rec:
        s = rec.events()
        assert s.t.tolist() == [16, 32] and s.x.tolist() == [3, 4]
        note = next(w for w in rec.warnings if "does not define" in w)
        assert note.startswith("2 word(s) of types 0x9, 0xC") and "word 4" in note


# -- text, npy, npz ----------------------------------------------------------------------------


def test_text_nan_time_on_the_first_line_is_refused_like_later_ones(tmp_path):
    for body in (b"nan 1 1 1\n0.2 2 2 0\n", b"64 48\nINF 1 1 1\n0.2 2 2 0\n"):
        f = tmp_path / "n.txt"
        f.write_bytes(body)
        with pytest.raises(InputError, match="event 0 has a non-finite time"):
            open_events(f)  # was: the line taken for a header, the event dropped


def test_text_with_a_field_too_many_is_refused_not_cut(tmp_path):
    f = tmp_path / "five.txt"
    f.write_bytes(b"0.1 1 1 1 9\n0.2 2 2 0 9\n")
    with pytest.raises(FormatError, match="event lines have 5 columns, expected 4 .*dropped"):
        open_events(f)
    s = open_events(f, ReadOptions(columns=("t", "x", "y", "p", "_"), sensor=(4, 4))).events()
    assert s.t.tolist() == [100_000, 200_000] and s.p.tolist() == [1, -1]
    later = tmp_path / "later.txt"  # one line further down with a fifth field
    later.write_bytes(b"0.1 1 1 1\n" * 5 + b"0.2 2 2 0 9\n")
    with pytest.raises(FormatError, match="near line 6: it has 5 fields"):
        open_events(later)


def test_npy_with_a_column_too_many_is_refused(tmp_path):
    f = tmp_path / "e.npy"
    np.save(f, np.array([[0.1, 1, 1, 1, 7], [0.2, 2, 2, 0, 7]]))
    with pytest.raises(FormatError, match="5 columns but 4 are named"):
        open_events(f)
    s = open_events(f, ReadOptions(columns=("t", "x", "y", "p", "_"))).events()
    assert s.t.tolist() == [100_000, 200_000]


def test_npz_with_a_2d_time_array_is_refused_not_flattened(tmp_path):
    f = tmp_path / "e.npz"
    np.savez(f, t=np.array([[10, 20], [30, 40]]), x=np.arange(4), y=np.arange(4),
             p=np.ones(4))
    with pytest.raises(FormatError, match=r"'t' has shape \(2, 2\), expected one value"):
        open_events(f)
    np.savez(f, t=np.array([[10], [20], [30], [40]]), x=np.arange(4), y=np.arange(4),
             p=np.ones(4))  # a column vector is one value per event
    assert open_events(f).events().t.tolist() == [10, 20, 30, 40]


# -- frames outside [0, 1] -------------------------------------------------------------------


def _frame_and_events(tmp_path: Path):
    from trmd_cli.events import Exposure, make_stream
    from trmd_cli.write import write_events_npz

    rng = np.random.default_rng(2)
    n = 3000
    s = make_stream(rng.integers(0, 64, n), rng.integers(0, 48, n),
                    np.sort(rng.integers(0, 50_000, n)), rng.integers(0, 2, n), 64, 48)
    write_events_npz(tmp_path / "ev.npz", s, [Exposure(5_000, 45_000)])
    return s, Exposure(5_000, 45_000)


def test_h5_frames_far_outside_0_1_are_said_and_clipped(tmp_path):
    from trmd_cli.write import write_h5

    s, win = _frame_and_events(tmp_path)
    frames = np.full((1, 48, 64), -1e30, np.float32)
    write_h5(tmp_path / "rec.h5", s, blurry=frames, exposures=[win])
    r = runner.invoke(app, ["deblur", str(tmp_path / "rec.h5"), "-o", str(tmp_path / "out"),
                            "--method", "edi", "--contrast", "0.2"])
    assert r.exit_code == 0, r.output
    assert "100 % of its pixel values lie outside [0, 1] (from -1e+30" in r.stderr


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_float_tiff_with_nan_or_inf_is_refused_alike(tmp_path, value):
    import cv2

    from trmd_cli.read import read_image

    img = np.full((48, 64), 0.5, np.float32)
    img[3, 4] = value
    cv2.imwrite(str(tmp_path / "b.tif"), img)
    with pytest.raises(InputError, match="1 pixel value.* NaN or infinite"):
        read_image(tmp_path / "b.tif")  # +inf was clipped to 1, NaN refused


def test_float_tiff_outside_0_1_is_said(tmp_path):
    import cv2

    _frame_and_events(tmp_path)
    img = np.full((48, 64), 0.5, np.float32)
    img[:12] = 1.5  # a quarter of the frame above white
    cv2.imwrite(str(tmp_path / "b.tif"), img)
    r = runner.invoke(app, ["deblur", str(tmp_path / "b.tif"), str(tmp_path / "ev.npz"), "-o",
                            str(tmp_path / "out"), "--method", "edi", "--contrast", "0.2"])
    assert r.exit_code == 0, r.output
    assert "25 % of its pixel values lie outside [0, 1] (from 0.5 to 1.5)" in r.stderr
