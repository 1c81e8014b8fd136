"""Property-based tests (hypothesis) for the readers, the writers and the voxelizer.

- every writer (npz, HDF5, text) → ``open_events`` gives back exactly the events written, and
  any time window of them;
- SCER voxels equal a brute-force reading of their definition, and are linear in the events;
- ``make_stream`` never changes the arrays it is given, whatever it decides about them;
- random bytes — alone, after a format's magic, or as damage to a valid file — make
  ``open_events`` and reading raise :class:`TrmdError` and nothing else.
"""

from __future__ import annotations

import functools
import os
import tempfile
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from trmd_cli.errors import InputError, TrmdError
from trmd_cli.events import EventStream, Exposure, make_stream
from trmd_cli.read import open_events
from trmd_cli.voxel import scer_voxels
from trmd_cli.write import write_events_npz, write_events_text, write_h5

# In CI the examples are the same every run: a new failure there should be a code change's
SETTINGS = dict(deadline=None, database=None, derandomize=bool(os.environ.get("CI")),
                suppress_health_check=[HealthCheck.too_slow])


@st.composite
def event_streams(draw, min_events: int = 0, max_events: int = 60,
                  size: tuple[int, int] | None = None) -> EventStream:
    """Sorted streams on a random sensor; times either crowded (many equal) or spread to 2**40."""
    w, h = size or (draw(st.integers(1, 400)), draw(st.integers(1, 300)))
    n = draw(st.integers(min_events, max_events))
    top = draw(st.sampled_from([5, 10_000, 2**40]))
    t = sorted(draw(st.lists(st.integers(0, top), min_size=n, max_size=n)))
    x = draw(st.lists(st.integers(0, w - 1), min_size=n, max_size=n))
    y = draw(st.lists(st.integers(0, h - 1), min_size=n, max_size=n))
    p = draw(st.lists(st.sampled_from([-1, 1]), min_size=n, max_size=n))
    return make_stream(np.array(x, np.int64), np.array(y, np.int64), np.array(t, np.int64),
                       np.array(p, np.int64), w, h)


def assert_same(a: EventStream, b: EventStream) -> None:
    assert (a.width, a.height) == (b.width, b.height)
    for k in "xytp":
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
        assert getattr(a, k).dtype == getattr(b, k).dtype, k


# -- writers → readers ---------------------------------------------------------------------------


@settings(max_examples=40, **SETTINGS)
@given(s=event_streams(), fmt=st.sampled_from(["npz", "h5", "txt"]), data=st.data())
def test_every_writer_round_trips_exactly(s, fmt, data):
    if fmt == "txt" and len(s) == 0:
        return  # a text file of no events is a size line alone: refused (test_bad_input)
    windows = None
    if fmt == "npz" and len(s):
        starts = data.draw(st.lists(st.integers(0, int(s.t[-1])), max_size=3))
        windows = [Exposure(a, a + data.draw(st.integers(1, 10**6))) for a in starts]
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"events.{fmt}"
        {"npz": lambda: write_events_npz(path, s, windows),
         "h5": lambda: write_h5(path, s),
         "txt": lambda: write_events_text(path, s)}[fmt]()
        with open_events(path) as rec:
            assert rec.num_events() == len(s)
            assert rec.time_range_us() == s.time_range_us
            assert_same(rec.events(), s)
            if windows:
                assert rec.stored_windows() == windows
            # any window, as the voxelizer asks for it
            if len(s):
                a = data.draw(st.integers(-1, int(s.t[-1]) + 1))
                b = data.draw(st.integers(a, int(s.t[-1]) + 2))
                assert_same(rec.events(a, b), s.slice(a, b))
            assert_same(EventStream.concatenate(list(rec.iter_chunks())) if len(s) else s, s)


# -- the voxelizer -------------------------------------------------------------------------------


def brute_force_scer(s: EventStream, e: Exposure, n: int) -> np.ndarray:
    """Eq. 13 read literally, one event at a time, in Python integers."""
    m = 2 * n
    b = np.zeros((m, s.height, s.width), np.int64)
    for x, y, t, p in zip(s.x.tolist(), s.y.tolist(), s.t.tolist(), s.p.tolist(), strict=True):
        if e.start_us <= t <= e.end_us:
            j = min((t - e.start_us) * m // e.duration_us, m - 1)
            b[j, y, x] += p
    channels = [-b[k:n].sum(0) if k < n else b[n:k].sum(0) for k in range(2 * n + 1) if k != n]
    return np.stack(channels).astype(np.float32)


@st.composite
def exposures(draw, top: int = 10_000) -> Exposure:
    start = draw(st.integers(0, top))
    return Exposure(start, start + draw(st.integers(1, top)))


@settings(max_examples=60, **SETTINGS)
@given(s=event_streams(max_events=80, size=(5, 4)), e=exposures(), n=st.integers(1, 4))
def test_voxels_equal_brute_force_definition(s, e, n):
    np.testing.assert_array_equal(scer_voxels(s, e, n), brute_force_scer(s, e, n))


@settings(max_examples=40, **SETTINGS)
@given(a=event_streams(max_events=60, size=(6, 3)), b=event_streams(max_events=60, size=(6, 3)),
       e=exposures(), n=st.integers(1, 3))
def test_voxels_are_linear_in_the_events(a, b, e, n):
    both = EventStream.concatenate([a, b])
    both = both.take(np.argsort(both.t, kind="stable"))
    np.testing.assert_array_equal(scer_voxels(both, e, n),
                                  scer_voxels(a, e, n) + scer_voxels(b, e, n))
    flipped = EventStream(a.x, a.y, a.t, (-a.p).astype(np.int8), a.width, a.height)
    np.testing.assert_array_equal(scer_voxels(flipped, e, n), -scer_voxels(a, e, n))


# -- make_stream ---------------------------------------------------------------------------------


def columns(n: int):
    ints = st.integers(-3, 70)
    floats = st.one_of(st.floats(-1.0, 80.0), st.sampled_from([np.nan, np.inf, -np.inf]))
    col = st.one_of(st.lists(ints, min_size=n, max_size=n).map(np.array),
                    st.lists(floats, min_size=n, max_size=n).map(np.array),
                    st.lists(st.integers(0, 70), min_size=n, max_size=n)
                    .map(lambda v: np.array(v, np.uint16)))
    pol = st.one_of(col, st.lists(st.booleans(), min_size=n, max_size=n).map(np.array),
                    st.lists(st.sampled_from([-1, 0, 1]), min_size=n, max_size=n)
                    .map(lambda v: np.array(v, np.int8)))
    return st.tuples(col, col, col, pol)


@settings(max_examples=80, **SETTINGS)
@given(data=st.data(), n=st.integers(0, 12), sort=st.booleans(),
       size=st.one_of(st.none(), st.tuples(st.integers(1, 80), st.integers(1, 80))))
def test_make_stream_never_mutates_its_inputs(data, n, sort, size):
    x, y, t, p = data.draw(columns(n))
    before = [(a.copy(), a.dtype, a.flags.writeable) for a in (x, y, t, p)]
    w, h = size or (None, None)
    try:
        s = make_stream(x, y, t, p, w, h, sort=sort)
    except InputError:
        s = None
    for a, (copy, dtype, writeable) in zip((x, y, t, p), before, strict=True):
        assert a.dtype == dtype and a.flags.writeable == writeable
        np.testing.assert_array_equal(a, copy)
    if s is not None:  # what was accepted is valid
        assert (np.diff(s.t) >= 0).all() and set(np.unique(s.p)) <= {-1, 1}
        assert len(s) == 0 or (s.x.max() < s.width and s.y.max() < s.height)


# -- random bytes --------------------------------------------------------------------------------

#: starts that send random bytes deep into each reader
MAGIC = {
    "text": b"64 48\n0.000001 1 2 1\n",
    "npy": b"\x93NUMPY\x01\x00v\x00{'descr': '<f8', 'fortran_order': False, 'shape': (3, 4), }",
    "npz": b"PK\x03\x04",
    "hdf5": b"\x89HDF\r\n\x1a\n",
    "aedat4": b"#!AER-DAT4.0\r\n",
    "evt2": b"% evt 2.0\n% geometry 64x48\n",
    "evt3": b"% evt 3.0\n% format EVT3;height=48;width=64\n% end\n",
    "dat": b"% Width 64\n% Height 48\n\x0c\x08",
    "mat": b"MATLAB 5.0 MAT-file, Platform: posix".ljust(116) + bytes(8) + b"\x00\x01IM",
    "aedat2": b"#!AER-DAT2.0\r\n# AEChip: eu.seebetter.ini.chips.davis.DAVIS240C\r\n"
              b"#End Of ASCII Header\r\n",
    "aedat3": b"#!AER-DAT3.1\r\n#Format: RAW\r\n#Source 1: DAVIS240C\r\n#!END-HEADER\r\n",
    "rosbag1": b"#ROSBAG V2.0\n",
    "none": b"",
}
EXTENSIONS = [".txt", ".npy", ".npz", ".h5", ".aedat4", ".raw", ".dat", ".mat", ".bin",
              ".aedat", ".bag"]


def read_everything(path: Path) -> None:
    with open_events(path) as rec:
        rec.events()
        rec.time_range_us()
        for _ in rec.iter_chunks():
            pass
        rec.frame_exposures()
        rec.stored_windows()
        for _ in rec.frames():
            pass


def only_trmd_errors(path: Path) -> None:
    try:
        read_everything(path)
    except TrmdError as e:
        assert e.path is not None, f"error without the file: {e}"


@settings(max_examples=150, **SETTINGS)
@given(magic=st.sampled_from(sorted(MAGIC)), body=st.binary(max_size=600),
       ext=st.sampled_from(EXTENSIONS))
def test_random_bytes_raise_only_trmd_errors(magic, body, ext):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"f{ext}"
        path.write_bytes(MAGIC[magic] + body)
        only_trmd_errors(path)


def _valid_files(folder: Path) -> dict[str, Path]:
    import h5py
    import scipy.io as sio

    from tests.helpers.camera import dat_bytes, evt2_bytes, good

    rng = np.random.default_rng(3)
    s = make_stream(rng.integers(0, 64, 40), rng.integers(0, 48, 40),
                    np.sort(rng.integers(0, 10_000, 40)), rng.integers(0, 2, 40), 64, 48)
    files = {f: good(folder, f) for f in ("txt", "npz", "npy", "h5", "mat")}
    files["raw"] = folder / "e.raw"
    files["raw"].write_bytes(evt2_bytes(s.t, s.x, s.y, s.p))
    files["dat"] = folder / "e.dat"
    files["dat"].write_bytes(dat_bytes(s.t, s.x, s.y, s.p))
    files["esl.mat"] = folder / "esl.mat"
    sio.savemat(files["esl.mat"], {"section_event_timestamp": s.t[None] / 1e6,
                                   "section_event_x": s.x[None], "section_event_y": s.y[None],
                                   "section_event_polarity": (s.p[None] > 0),
                                   "start_timestamp": [[0.0]], "end_timestamp": [[0.01]]})
    files["eu.h5"] = folder / "eu.h5"
    with h5py.File(files["eu.h5"], "w") as f:
        f.attrs["sensor_resolution"] = (48, 64)
        for k, v in dict(xs=s.x, ys=s.y, ts=s.t / 1e6, ps=s.p > 0).items():
            f[f"events/{k}"] = v
    files["frames.h5"] = folder / "frames.h5"
    write_h5(files["frames.h5"], s, blurry=np.full((2, 48, 64), 0.5, np.float32),
             exposures=[Exposure(0, 4000), Exposure(5000, 9000)])
    return files


@functools.cache
def valid_files() -> dict[str, bytes]:
    """Small valid files of every layout, as bytes (built once per test session)."""
    with tempfile.TemporaryDirectory() as d:
        return {name: path.read_bytes() for name, path in _valid_files(Path(d)).items()}


@settings(max_examples=150, **SETTINGS)
@given(data=st.data())
def test_damaged_valid_files_raise_only_trmd_errors(data):
    files = valid_files()
    name = data.draw(st.sampled_from(sorted(files)), label="file")
    raw = bytearray(files[name])
    for _ in range(data.draw(st.integers(1, 6), label="damages")):
        at = data.draw(st.integers(0, len(raw) - 1), label="at")
        span = data.draw(st.integers(1, 16), label="span")
        raw[at:at + span] = data.draw(st.binary(min_size=span, max_size=span), label="bytes")
    if data.draw(st.booleans(), label="cut"):
        raw = raw[: data.draw(st.integers(1, len(raw)), label="cut at")]
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / (name if "." in name else f"damaged.{name}")
        path.write_bytes(bytes(raw))
        only_trmd_errors(path)
