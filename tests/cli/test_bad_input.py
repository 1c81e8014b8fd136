"""The bad-input matrix: malformed files of every format the readers support, fed to the readers
and to `trmd info`, `trmd voxelize` and `trmd convert`.

Every case builds its damaged file in ``tmp_path`` (real recordings from ../shared/data are cut
or flipped into ``tmp_path`` too, and skipped when absent). Library: opening and reading raise a
:class:`TrmdError` that names the file. CLI: exit code 2, one ``error:`` line on stderr naming
the file and carrying a hint (``— how to fix``), no traceback, and the output path absent — or,
when it existed before, byte-identical.
"""

from __future__ import annotations

import re
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.camera import dat_bytes, evt2_bytes, good, stream
from tests.helpers.cli import assert_one_error_line
from tests.helpers.data import SHARED
from trmd_cli.cli.app import app
from trmd_cli.errors import FormatError, InputError, TrmdError
from trmd_cli.events import Exposure, make_stream
from trmd_cli.read import open_events, read_image
from trmd_cli.read.folders import open_frame_folder
from trmd_cli.write import write_h5

REC = SHARED / "recordings"
W, H = 64, 48
ALL = ("info", "voxelize", "convert")
runner = CliRunner()


# -- small, real-ish files of every format -----------------------------------------------------


def cut(data: bytes, frac: float) -> bytes:
    return data[: int(len(data) * frac)]


def flipped(data: bytes, at: int, n: int = 8, value: int = 0xFF) -> bytes:
    b = bytearray(data)
    at = at if at >= 0 else len(b) + at
    b[at:at + n] = bytes([value]) * len(b[at:at + n])
    return bytes(b)


def text_cut_mid_line(data: bytes, frac: float) -> bytes:
    """Cut just after the first field of a line, so the last line is short, never whole."""
    i = data.index(b" ", int(len(data) * frac))
    return data[: i + 1]


def h5_file(path: Path, events: dict, attrs: dict | None = None, extra: dict | None = None):
    with h5py.File(path, "w") as f:
        f.attrs.update(attrs or {})
        for k, v in events.items():
            f[f"events/{k}"] = v
        for k, v in (extra or {}).items():
            f[k] = v
    return path


def trmd_h5(path: Path, **frames) -> Path:
    """trmd layout: 4 events on a 4x4 sensor and the given frames/* datasets."""
    return h5_file(path, dict(x=[0, 1, 2, 3], y=[0, 1, 2, 3], t=[10, 20, 30, 40], p=[1, -1, 1, 1]),
                   dict(format="trmd", width=4, height=4),
                   {f"frames/{k}": v for k, v in frames.items()})


def npz_file(path: Path, **arrays) -> Path:
    base = dict(x=np.array([1, 2]), y=np.array([1, 2]), t=np.array([10, 20]),
                p=np.array([1, 0]), width=np.int64(W), height=np.int64(H))
    base.update(arrays)
    np.savez(path, **{k: v for k, v in base.items() if v is not None})
    return path


def mat_file(path: Path, **variables) -> Path:
    import scipy.io as sio

    sio.savemat(path, variables)
    return path


def shared_copy(tmp: Path, name: str, damage: Callable[[bytes], bytes]) -> Path:
    if not (REC / name).exists():
        pytest.skip("../shared/data/recordings is absent")
    out = tmp / f"damaged_{name}"
    out.write_bytes(damage((REC / name).read_bytes()))
    return out


# -- the matrix ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Case:
    """One malformed input. ``needle``: regex the error line must match. ``commands``: those
    that must refuse it (others may legitimately accept it). ``args``: extra CLI options."""

    id: str
    build: Callable[[Path], Path]
    needle: str
    commands: tuple[str, ...] = ALL
    args: tuple[str, ...] = ()
    lib: bool = True  # the reader itself refuses it (not only a command)
    names: str | None = None  # what the line must name, when not the file (a bad option)


TRUNC = "truncated|corrupt|incomplete|partial|cannot be read|not a readable|malformed"
TXT = b"%d %d\n" % (W, H)

CASES = [
    # ---- text
    Case("text-empty-file", lambda d: _w(d / "e.txt", b""), "file is empty"),
    Case("text-cut-30%", lambda d: _w(d / "c.txt", text_cut_mid_line(
        good(d, "txt").read_bytes(), 0.3)), r"malformed event line near line \d+"),
    Case("text-cut-99%", lambda d: _w(d / "c.txt", text_cut_mid_line(
        good(d, "txt").read_bytes(), 0.99)), "malformed event line"),
    Case("text-cut-in-size-line", lambda d: _w(d / "c.txt", TXT[:3]), "1 columns"),
    Case("text-binary-bytes", lambda d: _w(d / "b.txt", flipped(good(d, "txt").read_bytes(),
                                                                 200, 4, 0x00)),
         "unknown event file format"),
    Case("text-invalid-utf8", lambda d: _w(d / "u.txt", flipped(good(d, "txt").read_bytes(),
                                                                 5000, 2)), "malformed|utf-8"),
    Case("text-header-only", lambda d: _w(d / "h.txt", TXT + b"# t x y p\n"), "no event lines"),
    Case("text-nan-time", lambda d: _w(d / "n.txt", TXT + b"0.1 1 1 1\nnan 2 2 0\n"),
         "non-finite time"),
    Case("text-inf-time", lambda d: _w(d / "i.txt", TXT + b"0.1 1 1 1\ninf 2 2 0\n"),
         "non-finite time"),
    Case("text-negative-time", lambda d: _w(d / "g.txt", TXT + b"-0.1 1 1 1\n0.2 2 2 0\n"),
         "negative time"),
    Case("text-huge-time", lambda d: _w(d / "t.txt", TXT + b"1e300 1 1 1\n"), "out of range"),
    Case("text-unsorted", lambda d: _w(d / "s.txt", TXT + b"0.3 1 1 1\n0.2 2 2 0\n"),
         "not sorted"),
    Case("text-x-outside-sensor", lambda d: _w(d / "o.txt", TXT + b"0.1 1 1 1\n0.2 64 2 0\n"),
         "outside the sensor width 64"),
    Case("text-y-outside-sensor", lambda d: _w(d / "o.txt", TXT + b"0.1 1 48 1\n"),
         "outside the sensor height 48"),
    Case("text-negative-x", lambda d: _w(d / "o.txt", TXT + b"0.1 -1 4 1\n"), "negative"),
    Case("text-bad-polarity", lambda d: _w(d / "p.txt", TXT + b"0.1 1 1 5\n"), "polarity"),
    Case("text-fractional-x", lambda d: _w(d / "f.txt", TXT + b"0.1 1.5 1 1\n"), "whole numbers"),
    Case("text-three-columns", lambda d: _w(d / "3.txt", TXT + b"0.1 1 1\n"), "3 columns"),
    Case("text-letters", lambda d: _w(d / "l.txt", TXT + b"0.1 1 1 1\n0.2 a 1 1\n"),
         "near line 3"),
    Case("text-zero-size-line", lambda d: _w(d / "z.txt", b"0 48\n0.1 1 1 1\n"),
         "not a sensor size"),
    Case("text-sensor-option-too-small", lambda d: good(d, "txt"), "outside the sensor",
         args=("--sensor", "10x10"), lib=False),
    # ---- npz
    *[Case(f"npz-cut-{int(f * 100)}%", lambda d, f=f: _w(d / "c.npz", cut(
        good(d, "npz").read_bytes(), f)), TRUNC) for f in (0.002, 0.4, 0.999)],
    Case("npz-flip-array-header", lambda d: _w(d / "f.npz", flipped(
        good(d, "npz").read_bytes(), 100)), "cannot be read"),
    Case("npz-flip-array-data", lambda d: _w(d / "f.npz", flipped(
        good(d, "npz").read_bytes(), 20_000)), "CRC|cannot be read"),
    Case("npz-flip-central-directory-offset", lambda d: _w(d / "f.npz", flipped(
        good(d, "npz").read_bytes(), -6, 4)), TRUNC),
    Case("npz-compressed-corrupt", lambda d: _w(d / "z.npz", flipped(_compressed(d), 600, 32)),
         TRUNC),
    Case("npz-pickled", lambda d: npz_file(d / "k.npz", x=np.array([1, 2], object)),
         "pickled"),
    Case("npz-missing-p", lambda d: npz_file(d / "m.npz", p=None), "no event arrays"),
    Case("npz-no-arrays", lambda d: _savez(d / "0.npz"), "no event arrays"),
    Case("npz-nan-time", lambda d: npz_file(d / "n.npz", t=np.array([0.1, np.nan])),
         "non-finite time"),
    Case("npz-negative-time", lambda d: npz_file(d / "g.npz", t=np.array([-5, 2])),
         "negative time"),
    Case("npz-unsorted", lambda d: npz_file(d / "s.npz", t=np.array([5, 2])), "not sorted"),
    Case("npz-outside-sensor", lambda d: npz_file(d / "o.npz", x=np.array([1, 99])),
         "outside the sensor width"),
    Case("npz-negative-x", lambda d: npz_file(d / "o.npz", x=np.array([1, -3])), "negative"),
    Case("npz-length-mismatch", lambda d: npz_file(d / "l.npz", x=np.array([1, 2, 3])),
         "differ in length"),
    Case("npz-string-x", lambda d: npz_file(d / "s.npz", x=np.array(["a", "b"])), "type"),
    Case("npz-complex-time", lambda d: npz_file(d / "c.npz", t=np.array([1j, 2])),
         "expected numbers"),
    Case("npz-nan-polarity", lambda d: npz_file(d / "p.npz", p=np.array([1, np.nan])),
         "polarity"),
    Case("npz-empty-width", lambda d: npz_file(d / "w.npz", width=np.array([])),
         "expected one whole number"),
    Case("npz-zero-width", lambda d: npz_file(d / "w.npz", width=np.int64(0)),
         "not a whole number in 1..65535"),
    Case("npz-huge-width", lambda d: npz_file(d / "w.npz", width=np.int64(10**12)),
         "not a whole number in 1..65535"),
    Case("npz-window-reversed", lambda d: npz_file(d / "r.npz", exposure_start=[15],
                                                   exposure_end=[12]), "empty or reversed"),
    Case("npz-window-nan", lambda d: npz_file(d / "r.npz", exposure_start=[np.nan],
                                              exposure_end=[3.0]), "exposure_start"),
    Case("npz-window-count-mismatch", lambda d: npz_file(d / "r.npz", exposure_start=[1, 2],
                                                         exposure_end=[5]), "exposure_end 1"),
    # ---- npy
    Case("npy-cut", lambda d: _w(d / "c.npy", cut(good(d, "npy").read_bytes(), 0.7)),
         "not a valid NumPy file"),
    Case("npy-header-only", lambda d: _w(d / "c.npy", good(d, "npy").read_bytes()[:40]),
         "not a valid NumPy file"),
    Case("npy-header-unterminated-string", lambda d: _w(d / "h.npy", _npy_header(
        b"{'descr': '<f8', 'fortran_order': False, 'shape': (3, 4), '''")),
         "not a valid NumPy file|cannot be read"),  # numpy raised tokenize.TokenError
    Case("npy-pickled", lambda d: _npy(d / "k.npy", np.array([{"a": 1}], object)), "pickled"),
    Case("npy-1d", lambda d: _npy(d / "v.npy", np.arange(5)), "not an event list"),
    Case("npy-3-columns", lambda d: _npy(d / "3.npy", np.ones((5, 3))), "not an event list"),
    Case("npy-unnamed-fields", lambda d: _npy(d / "s.npy", np.zeros(3, [("a", "i4")])),
         "lack t/x/y/p"),
    Case("npy-nan-time", lambda d: _npy(d / "n.npy", np.array([[0.1, 1, 1, 1], [np.nan, 1, 1, 1]])),
         "non-finite time"),
    Case("npy-unsorted", lambda d: _npy(d / "u.npy", np.array([[9, 1, 1, 1], [3, 1, 1, 1]])),
         "not sorted"),
    # ---- HDF5: trmd, event_utils and DSEC layouts
    *[Case(f"h5-cut-{int(f * 100)}%", lambda d, f=f: _w(d / "c.h5", cut(
        good(d, "h5").read_bytes(), f)), TRUNC) for f in (0.001, 0.3, 0.95)],
    Case("h5-flip-superblock", lambda d: _w(d / "f.h5", flipped(good(d, "h5").read_bytes(), 10)),
         TRUNC),
    Case("h5-flip-magic", lambda d: _w(d / "f.h5", flipped(good(d, "h5").read_bytes(), 0)),
         "not the content of a HDF5"),
    Case("h5-no-events-group", lambda d: h5_file(d / "g.h5", {}, extra={"x": [1]}),
         "no 'events' group"),
    Case("h5-missing-p", lambda d: h5_file(d / "m.h5", dict(x=[1], y=[1], t=[1])),
         "lacks x/y/t/p"),
    Case("h5-length-mismatch", lambda d: h5_file(d / "l.h5", dict(x=[1, 2, 3], y=[1, 2],
                                                                  t=[1, 2], p=[1, 0])),
         "differ in length"),
    Case("h5-2d-dataset", lambda d: h5_file(d / "2.h5", {k: np.ones((2, 2)) for k in "xytp"}),
         "1-D numeric dataset"),
    Case("h5-string-dataset", lambda d: h5_file(d / "s.h5", {k: np.array([b"a"]) for k in "xytp"}),
         "1-D numeric dataset"),
    Case("h5-group-not-dataset", lambda d: _h5_groups(d / "g.h5"), "is a group"),
    Case("h5-unsorted-deep-inside", lambda d: _h5_unsorted(d / "u.h5"), "not sorted"),
    Case("h5-x-outside-sensor", lambda d: h5_file(d / "o.h5", dict(x=[0, 9], y=[0, 1], t=[1, 2],
                                                                   p=[1, 0]),
                                                  dict(width=4, height=4)), "outside the sensor"),
    Case("h5-bad-width-attr", lambda d: h5_file(d / "a.h5", dict(x=[0], y=[0], t=[1], p=[1]),
                                                dict(width="abc", height=4)), "sensor size"),
    Case("h5-zero-width-attr", lambda d: h5_file(d / "a.h5", dict(x=[0], y=[0], t=[1], p=[1]),
                                                 dict(width=0, height=4)), "sensor size"),
    Case("h5-trmd-window-reversed", lambda d: trmd_h5(d / "r.h5", exposure_start=[30],
                                                      exposure_end=[20]), "empty or reversed",
         commands=ALL),
    Case("h5-trmd-window-without-end", lambda d: trmd_h5(d / "e.h5", exposure_start=[30]),
         "without frames/exposure_end"),
    Case("h5-trmd-frame-size-mismatch", lambda d: trmd_h5(
        d / "z.h5", blurry=np.zeros((1, 5, 7), np.float32), exposure_start=[10],
        exposure_end=[40]), "frame 0 is 7x5 but the events' sensor is 4x4",
        commands=("convert",)),
    Case("h5-event_utils-nan-time", lambda d: h5_file(
        d / "n.h5", dict(xs=[0, 1], ys=[0, 1], ts=[0.1, np.nan], ps=[1, 0]),
        dict(sensor_resolution=(4, 4))), "non-finite time"),
    Case("h5-event_utils-short-resolution", lambda d: h5_file(
        d / "r.h5", dict(xs=[0, 1], ys=[0, 1], ts=[0.1, 0.2], ps=[1, 0]),
        dict(sensor_resolution=[4])), "sensor size"),
    Case("h5-dsec-negative-offset", lambda d: h5_file(
        d / "d.h5", dict(x=[0, 1], y=[0, 1], t=[10, 20], p=[1, 0]), dict(width=4, height=4),
        {"t_offset": np.int64(-1000)}), "negative"),
    Case("h5-dsec-empty-offset", lambda d: h5_file(
        d / "d.h5", dict(x=[0, 1], y=[0, 1], t=[10, 20], p=[1, 0]), dict(width=4, height=4),
        {"t_offset": np.zeros(0)}), "t_offset"),
    # ---- Prophesee EVT 2.0 (.raw)
    Case("evt2-cut-mid-word", lambda d: _w(d / "c.raw", good(d, "raw").read_bytes()[:-3]),
         "partial 32-bit word"),
    Case("evt2-cut-in-header", lambda d: _w(d / "c.raw", b"% ev"), "no known event format"),
    Case("evt2-undefined-word", lambda d: _w(d / "u.raw", flipped(good(d, "raw").read_bytes(),
                                                                   -400, 4, 0x22)),
         "EVT 2.0 does not define"),
    Case("evt2-time-goes-back", lambda d: _w(d / "b.raw", evt2_bytes(
        [100, 5000, 64], [1, 2, 3], [1, 2, 3], [1, 1, 0])), "goes back in time"),
    Case("evt2-x-outside-geometry", lambda d: _w(d / "o.raw", evt2_bytes(
        [1, 2], [100, 1], [1, 1], [1, 0])), "outside the 64x48 sensor"),
    Case("evt2-header-says-other", lambda d: _w(d / "o.raw", b"% evt 2.1\n" + bytes(16)),
         "not supported"),
    # ---- Prophesee EVT 3.0 (.raw)
    Case("evt3-odd-length", lambda d: _w(d / "o.raw", _EVT3_HEAD + bytes(101)),
         "partial 16-bit word"),
    Case("evt3-garbage", lambda d: _w(d / "g.raw", _EVT3_HEAD + _noise(4000, 3)), TRUNC + "|back"),
    # ---- Prophesee .dat
    Case("dat-cut-mid-record", lambda d: _w(d / "c.dat", good(d, "dat").read_bytes()[:-5]),
         "partial 8-byte event record"),
    # cut inside a header line: nothing after it to take for event data
    Case("dat-cut-in-header", lambda d: _w(d / "c.dat", good(d, "dat").read_bytes()[:40]),
         "ends inside its header"),
    Case("dat-cut-in-type-bytes", lambda d: _w(d / "c.dat", good(d, "dat").read_bytes()[:51]),
         "no event type/size"),
    Case("dat-bad-polarity", lambda d: _w(d / "p.dat", flipped(good(d, "dat").read_bytes(),
                                                               1003, 1, 0x70)), "polarity"),
    Case("dat-event-size-4", lambda d: _w(d / "s.dat", dat_bytes([1, 2], [1, 2], [1, 2], [1, 0],
                                                                 ev_size=4)), "event size 4"),
    Case("dat-time-goes-back", lambda d: _w(d / "b.dat", dat_bytes([10, 5], [1, 2], [1, 2],
                                                                   [1, 0])), "goes back in time"),
    Case("dat-garbage", lambda d: _w(d / "g.dat", _noise(1000, 4)), "not the content"),
    # ---- AEDAT 4 (the aedat decoder panics on some damaged headers)
    Case("aedat4-magic-then-zeros", lambda d: _w(d / "z.aedat4", b"#!AER-DAT4.0\r\n" + bytes(100)),
         "not a readable AEDAT 4 file"),
    Case("aedat4-magic-only", lambda d: _w(d / "m.aedat4", b"#!AER-DAT4.0\r\n"),
         "not a readable AEDAT 4 file"),
    Case("aedat30-unsupported", lambda d: _w(d / "a.aedat", b"#!AER-DAT3.0\r\n" + bytes(64)),
         "not supported"),
    # ---- MATLAB .mat
    *[Case(f"mat-cut-{int(f * 100)}%", lambda d, f=f: _w(d / "c.mat", cut(
        good(d, "mat").read_bytes(), f)), TRUNC + "|no events found") for f in (0.1, 0.5, 0.9)],
    Case("mat-flip-header", lambda d: _w(d / "f.mat", flipped(good(d, "mat").read_bytes(), 140)),
         "not a readable .mat file"),
    Case("mat-flip-data", lambda d: _w(d / "f.mat", flipped(good(d, "mat").read_bytes(), 200, 60)),
         "non-finite"),
    Case("mat-unknown-data-type", lambda d: _mat_unknown_type(d / "u.mat"),
         "not a readable .mat file"),  # scipy.io.loadmat died with SIGSEGV on this
    Case("mat-no-event-keys", lambda d: mat_file(d / "k.mat", foo=np.ones(3)), "no events found"),
    Case("mat-nan-time", lambda d: mat_file(d / "n.mat", t=[0.1, np.nan], x=[1, 2], y=[1, 2],
                                            p=[1, 0]), "non-finite time"),
    Case("mat-unsorted", lambda d: mat_file(d / "u.mat", t=[0.3, 0.1], x=[1, 2], y=[1, 2],
                                            p=[1, 0]), "not sorted"),
    Case("mat-length-mismatch", lambda d: mat_file(d / "l.mat", t=[0.1, 0.3], x=[1, 2, 3],
                                                   y=[1, 2], p=[1, 0]), "differ in length"),
    Case("mat-events-3-columns", lambda d: mat_file(d / "e.mat", events=np.ones((5, 3))),
         "expected N×4"),
    Case("mat-esl-window-reversed", lambda d: mat_file(
        d / "w.mat", section_event_timestamp=[[0.1, 0.2]], section_event_x=[[1, 2]],
        section_event_y=[[1, 2]], section_event_polarity=[[1, 0]], start_timestamp=[[0.3]],
        end_timestamp=[[0.2]]), "empty or reversed"),
    # (info describes a bins file; the commands that need events refuse it)
    Case("mat-binned", lambda d: mat_file(d / "b.mat", event_bins=np.zeros((2, 3, 3), np.int16)),
         "binned events", commands=tuple(c for c in ALL if c != "info")),
    # ---- any format
    Case("random-bytes-npz", lambda d: _w(d / "r.npz", _noise(2000, 5)), "not the content"),
    Case("random-bytes-no-extension", lambda d: _w(d / "r", _noise(2000, 6)),
         "unknown event file format"),
    Case("a-folder", lambda d: _mkdir(d / "events.npz"), "is a folder"),
    Case("missing-file", lambda d: d / "nowhere.npz", "file not found"),
    # ---- real recordings cut and flipped at various points (skipped without ../shared/data)
    *[Case(f"shared-{name}-{how}", lambda d, name=name, dmg=dmg: shared_copy(d, name, dmg),
           needle)
      for name, how, dmg, needle in [
          ("davis346.aedat4", "cut-0.05%", lambda b: cut(b, 0.0005), "not a readable AEDAT 4"),
          ("davis346.aedat4", "cut-0.2%", lambda b: cut(b, 0.002), "packet 2 cannot be decoded"),
          ("davis346.aedat4", "cut-50%", lambda b: cut(b, 0.5), "packet 350 cannot be decoded"),
          ("davis346.aedat4", "flip-header-20", lambda b: flipped(b, 20, 64),
           "not a readable AEDAT 4"),
          ("davis346.aedat4", "flip-xml-200", lambda b: flipped(b, 200, 64),
           "not a readable AEDAT 4"),
          ("davis346.aedat4", "noise-5000", lambda b: b[:5000] + _noise(64, 1) + b[5064:],
           "packet 0 cannot be decoded"),
          ("evt3.raw", "cut-last-byte", lambda b: b[:-1], "partial 16-bit word"),
          ("evt3.raw", "noise-4k", lambda b: b[:5000] + _noise(4096, 2) + b[9096:],
           "goes back in time"),
          ("evt2.raw", "cut-50%", lambda b: b[:1_054_571], "partial 32-bit word"),
          ("evt2.raw", "flip-300", lambda b: flipped(b, 300, 64), "outside the 640x480"),
          ("gen4.dat", "cut-in-header", lambda b: b[:20], "ends inside its header"),
          ("gen4.dat", "cut-1%", lambda b: cut(b, 0.01), "partial 8-byte event record"),
          ("gen4.dat", "flip-10000", lambda b: flipped(b, 10_000, 64), "polarity 15"),
      ]],
]

#: not reader errors: the file is fine, what is asked of it is not
CLI_CASES = [
    Case("window-outside-events", lambda d: good(d, "npz"), "outside the events' time range",
         commands=("voxelize",), args=("--exposure", "5000000", "6000000"), lib=False),
    Case("window-reversed", lambda d: good(d, "npz"), "empty or reversed",
         commands=("voxelize",), args=("--exposure", "6", "5"), lib=False, names="--exposure"),
    Case("stored-windows-all-outside", lambda d: npz_file(d / "w.npz", exposure_start=[500],
                                                          exposure_end=[600]),
         "lies outside the events' time range", commands=("voxelize",), lib=False),
    Case("offset-pushes-window-out", lambda d: good(d, "npz"), "outside the events' time range",
         commands=("voxelize",), args=("--time-offset", "-10s"), lib=False),
    Case("no-events-npz", lambda d: npz_file(d / "0.npz", **{k: np.zeros(0, int) for k in "xytp"}),
         "holds no events", commands=("voxelize", "convert"), lib=False),
    Case("no-events-h5", lambda d: write_h5(d / "0.h5", make_stream([], [], [], [], W, H)),
         "holds no events", commands=("voxelize", "convert"), lib=False),
    Case("no-events-evt2", lambda d: _w(d / "0.raw", b"% evt 2.0\n% geometry 64x48\n"),
         "holds no events", commands=("voxelize", "convert"), lib=False),
    Case("bad-time-unit", lambda d: good(d, "npz"), "days", args=("--time-unit", "days"),
         lib=False, names="--time-unit"),
    Case("bad-columns", lambda d: good(d, "txt"), "once each", args=("--columns", "t,x,x,p"),
         lib=False, names="--columns"),
    Case("bad-sensor-option", lambda d: good(d, "txt"), "not WxH", args=("--sensor", "64"),
         lib=False, names="--sensor"),
]


# -- builders' helpers --------------------------------------------------------------------------

_EVT3_HEAD = b"% evt 3.0\n% format EVT3;height=48;width=64\n% end\n"


def _w(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _noise(n: int, seed: int) -> bytes:
    return np.random.default_rng(seed).integers(0, 256, n, dtype=np.uint8).tobytes()


def _npy(path: Path, arr: np.ndarray) -> Path:
    np.save(path, arr, allow_pickle=True)
    return path


def _savez(path: Path, **arrays) -> Path:
    np.savez(path, **arrays)
    return path


def _mkdir(path: Path) -> Path:
    path.mkdir()
    return path


def _compressed(d: Path) -> bytes:
    s = stream()
    np.savez_compressed(d / "z0.npz", x=s.x, y=s.y, t=s.t, p=s.p, width=W, height=H)
    return (d / "z0.npz").read_bytes()


def _npy_header(header: bytes) -> bytes:
    header = header + b" " * (63 - len(header) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + bytes(96)


def _mat_unknown_type(path: Path) -> Path:
    """A MAT v5 file whose first variable's data element has type 63, which MAT does not define.
    Layout: 128-byte header, then miMATRIX (tag 8 bytes) holding flags (16 bytes), dimensions
    (8 + 8 for two), the name in a small element (8), then the data element's tag."""
    mat_file(path, t=np.arange(3.0))
    raw = bytearray(path.read_bytes())
    assert int.from_bytes(raw[128:132], "little") == 14  # miMATRIX, uncompressed
    tag = 128 + 8 + 16 + 16 + 8
    assert int.from_bytes(raw[tag:tag + 4], "little") == 9  # miDOUBLE, the data of 't'
    raw[tag:tag + 4] = (63).to_bytes(4, "little")
    return _w(path, bytes(raw))


def _h5_groups(path: Path) -> Path:
    with h5py.File(path, "w") as f:
        for k in "xytp":
            f.create_group(f"events/{k}")
    return path


def _h5_unsorted(path: Path) -> Path:
    """Times go back once, deep inside (between the reader's coarse index points)."""
    n = 20_000
    t = np.arange(n) * 10
    t[10_001] = 5
    return h5_file(path, dict(x=np.zeros(n, int), y=np.zeros(n, int), t=t, p=np.ones(n, int)),
                   dict(width=4, height=4))


# -- library ------------------------------------------------------------------------------------


def read_everything(path: Path) -> None:
    """What any command may ask of a recording."""
    with open_events(path) as rec:
        rec.num_events()
        rec.time_range_us()
        rec.events()
        for _ in rec.iter_chunks():
            pass
        rec.frame_exposures()
        rec.stored_windows()
        for _ in rec.frames():
            pass


@pytest.mark.parametrize("case", [c for c in CASES if c.lib], ids=lambda c: c.id)
def test_reader_refuses_with_typed_error_naming_the_file(case, tmp_path):
    path = case.build(tmp_path)
    with pytest.raises(TrmdError) as info:
        read_everything(path)
    e = info.value
    assert isinstance(e, (FormatError, InputError)), type(e)
    assert e.path is not None and Path(e.path).name == path.name, str(e)
    assert e.hint, f"no hint in {e}"
    assert re.search(case.needle, str(e)), str(e)


# -- CLI ----------------------------------------------------------------------------------------


def invoke(command: str, path: Path, out_dir: Path, extra: tuple[str, ...], previous: bool):
    """Run one command; returns (result, output path or None)."""
    out_dir.mkdir(exist_ok=True)
    out = None
    args = [command, str(path), *extra]
    if command == "voxelize":
        out = out_dir / "voxels.npz"
    elif command == "convert":
        out = out_dir / "events.h5"  # HDF5: its writer opens before reading the events
    if out is not None:
        args += ["-o", str(out)]
        if previous:
            out.write_bytes(b"the user's previous output")
            args.append("--overwrite")
    return runner.invoke(app, args), out


assert_one_clear_line = assert_one_error_line


def assert_output_untouched(out: Path | None, previous: bool) -> None:
    if out is None:
        return
    if previous:
        assert out.read_bytes() == b"the user's previous output"
    else:
        assert not out.exists()
    assert [p.name for p in out.parent.iterdir()] == ([out.name] if previous else [])


@pytest.mark.parametrize("case", CASES + CLI_CASES, ids=lambda c: c.id)
def test_cli_refuses_with_one_line_and_exit_2(case, tmp_path):
    src_dir = tmp_path / "in"
    src_dir.mkdir()
    path = case.build(src_dir)
    for i, command in enumerate(case.commands):
        previous = i % 2 == 1  # alternate: no output yet / an output the user already has
        for prev in (previous, not previous) if command == "convert" else (previous,):
            result, out = invoke(command, path, tmp_path / f"out-{command}-{prev}", case.args,
                                 prev)
            assert_one_clear_line(result, case.names or path.name, case.needle)
            assert_output_untouched(out, prev)


def test_info_describes_a_file_with_no_events(tmp_path):
    """`info` is how a user looks at a file: an empty recording is reported, not refused."""
    path = npz_file(tmp_path / "0.npz", **{k: np.zeros(0, int) for k in "xytp"})
    r = runner.invoke(app, ["info", str(path), "--json"])
    assert r.exit_code == 0, r.output
    assert '"events": 0' in r.stdout
    assert "holds no events" in r.stderr


@pytest.mark.parametrize("command", ["voxelize", "convert"])
def test_output_problems_are_one_line(tmp_path, command):
    src = good(tmp_path, "npz")
    ext = ".npz" if command == "voxelize" else ".h5"
    folder = tmp_path / f"out{ext}"
    folder.mkdir()
    (folder / "keep").write_bytes(b"x")
    for out, needle in [(folder, "already exists"),
                        (tmp_path / "no" / "such" / f"o{ext}", "parent folder does not exist")]:
        r = runner.invoke(app, [command, str(src), "-o", str(out)])
        assert r.exit_code == 2 and r.stderr.count("\n") == 1, r.output
        assert needle in r.stderr and "Traceback" not in r.output
    # --overwrite does not let a file replace a folder
    r = runner.invoke(app, [command, str(src), "-o", str(folder), "--overwrite"])
    assert r.exit_code == 2 and "is a folder" in r.stderr, r.output
    assert (folder / "keep").read_bytes() == b"x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["good.npz", folder.name]


# -- images (frames read for deblurring) ---------------------------------------------------------


@pytest.mark.parametrize("damage,needle", [
    (lambda png: b"", "not a readable image"),
    (lambda png: png[: len(png) // 2], "not a readable image"),
    (lambda png: png[:8] + bytes(len(png) - 8), "not a readable image"),
    (lambda png: b"0.1 1 1 1\n" * 20, "not a readable image"),
], ids=["empty", "cut-half", "zeroed-after-magic", "text-named-png"])
def test_unreadable_images_are_format_errors(tmp_path, damage, needle):
    import cv2

    ok, png = cv2.imencode(".png", np.full((H, W), 128, np.uint8))
    path = _w(tmp_path / "000001.png", damage(png.tobytes()))
    with pytest.raises(FormatError, match=needle) as info:
        read_image(path)
    assert info.value.path == str(path) and info.value.hint
    with pytest.raises(InputError, match="not found"):
        read_image(tmp_path / "missing.png")


def test_blurry_image_not_matching_the_sensor(tmp_path):
    import cv2

    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "000001.png"), np.zeros((H + 2, W), np.uint8))
    events = good(tmp_path, "npz")
    with pytest.raises(InputError, match=r"image is 64x50 but the events' sensor is 64x48") as e:
        open_frame_folder(frames, events, exposures=[Exposure(1_000, 500_000)])
    assert e.value.path.endswith("000001.png") and e.value.hint


# -- what a user really sees: real processes, so native code writing to fd 2 shows up too ----------


@pytest.mark.parametrize("case_id", ["aedat4-magic-then-zeros", "npz-cut-40%", "text-nan-time",
                                     "h5-trmd-frame-size-mismatch"])
def test_real_process_prints_one_line(tmp_path, case_id):
    case = next(c for c in CASES if c.id == case_id)
    path = case.build(tmp_path)
    out = tmp_path / "o.h5"
    out.write_bytes(b"before")
    env = {"RUST_BACKTRACE": "1"}  # worst case for a Rust panic message
    r = subprocess.run([sys.executable, "-m", "trmd_cli", "convert", str(path), "-o", str(out),
                        "--overwrite"], capture_output=True, text=True, timeout=120,
                       env={**_env(), **env})
    assert r.returncode == 2, r.stderr
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    assert path.name in lines[0] and re.search(case.needle, lines[0])
    assert "panicked" not in r.stderr and "Traceback" not in r.stderr
    assert out.read_bytes() == b"before"
    assert sorted(p.name for p in tmp_path.iterdir() if ".tmp" in p.name) == []


def _env() -> dict[str, str]:
    import os

    return {k: v for k, v in os.environ.items() if not k.startswith("PYTEST")}


# -- commands written alongside (each case skips while its command is not registered) ------------


def _registered(name: str) -> bool:
    return any((c.name or c.callback.__name__) == name for c in app.registered_commands)


def _png(d: Path, damage: Callable[[bytes], bytes], name: str = "still.png") -> Path:
    import cv2

    img = (np.random.default_rng(0).random((H, W)) * 255).astype(np.uint8)
    return _w(d / name, damage(cv2.imencode(".png", img)[1].tobytes()))


OTHER_CASES = [
    ("simulate", "image-cut-half", lambda d: _png(d, lambda b: b[: len(b) // 2]),
     "not a readable image", ()),
    ("simulate", "image-empty", lambda d: _png(d, lambda b: b""), "not a readable image", ()),
    ("simulate", "image-is-text", lambda d: _png(d, lambda b: b"0.1 1 1 1\n"),
     "not a readable image", ()),
    ("simulate", "video-without-index",
     lambda d: _w(d / "v.mp4", b"\0\0\0\x18ftypmp42" + bytes(99)), "not a readable video", ()),
    ("simulate", "empty-folder", lambda d: _mkdir(d / "frames"), "image file", ()),
    ("simulate", "missing-input", lambda d: d / "nowhere.png", "not found", ()),
    ("train", "recipe-not-toml", lambda d: _w(d / "bad.toml", b"this is = not [toml\n"),
     "not valid TOML", ("-r", "{path}", "-d", "{images}")),
    ("train", "init-weights-random-bytes", lambda d: _w(d / "w.safetensors", _noise(3000, 8)),
     "not a readable safetensors", ("--init-weights", "{path}", "-d", "{images}")),
    ("train", "init-weights-pickle", lambda d: _w(d / "w.safetensors", __import__("pickle").dumps(
        {"weights": [1.0, 2.0]})), "pickle", ("--init-weights", "{path}", "-d", "{images}")),
    ("train", "init-weights-foreign-safetensors",
     lambda d: _foreign_safetensors(d / "w.safetensors"), "without trmd metadata",
     ("--init-weights", "{path}", "-d", "{images}")),
    ("train", "data-missing", lambda d: d / "no-images", "not found", ("-d", "{path}")),
]


def _foreign_safetensors(path: Path) -> Path:
    from safetensors.numpy import save_file

    save_file({"weight": np.zeros((3, 3), np.float32)}, str(path))
    return path


@pytest.mark.parametrize("command,case_id,build,needle,args", OTHER_CASES,
                         ids=[f"{c.values[0]}-{c.values[1]}" if hasattr(c, "values") else
                              f"{c[0]}-{c[1]}" for c in OTHER_CASES])
def test_other_commands_refuse_with_one_line_and_exit_2(tmp_path, command, case_id, build, needle,
                                                        args):
    if not _registered(command):
        pytest.skip(f"`trmd {command}` is not built yet")
    src = tmp_path / "in"
    src.mkdir()
    path = build(src)
    images = src / "images"
    images.mkdir(exist_ok=True)
    for i in range(2):
        _png(images, lambda b: b, f"{i:06d}.png")
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    if command == "simulate":
        out = out_dir / "sim.h5"
        out.write_bytes(b"the user's previous output")
        argv = ["simulate", str(path), "-o", str(out), "--overwrite"]
    else:
        out = out_dir / "run"
        out.mkdir()
        (out / "log.txt").write_bytes(b"the user's previous output")
        argv = ["train", *[a.format(path=path, images=images) for a in args], "-o", str(out),
                "--overwrite", "--set", "train.steps=1"]
    result = runner.invoke(app, argv)
    assert_one_clear_line(result, path.name, needle)
    if command == "simulate":
        assert out.read_bytes() == b"the user's previous output"
    else:
        assert [p.name for p in out.iterdir()] == ["log.txt"]
        assert (out / "log.txt").read_bytes() == b"the user's previous output"
    assert [p.name for p in out_dir.iterdir()] == [out.name]
