"""`.npz` and text read a piece at a time: the same events as reading the file whole, every
window and piece; only the pieces a window needs are read again; damage is still named.

Small chunks (and no in-memory cache) stand in for recordings of hundreds of millions of events;
their memory is measured by ``bench/bench_memory.py --readers``.
"""

from __future__ import annotations

import zipfile

import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.data import random_stream
from trmd_cli.cli.app import app
from trmd_cli.errors import FormatError, InputError
from trmd_cli.events import EventStream, Exposure
from trmd_cli.read import ReadOptions, chunked, npz, open_events, text
from trmd_cli.write import write_events_npz, write_events_text


@pytest.fixture
def small_pieces(monkeypatch):
    """Chunks of 500 events (npz), blocks of 4 kB (text), nothing kept in memory."""
    monkeypatch.setattr(chunked, "CACHE_MAX_EVENTS", 0)
    monkeypatch.setattr(npz, "NPZ_CHUNK_EVENTS", 500)
    monkeypatch.setattr(text, "TEXT_BLOCK_BYTES", 4096)


def same(a: EventStream, b: EventStream) -> None:
    for k in "xytp":
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))


@pytest.mark.parametrize("kind", ["npz", "npz-compressed", "txt"])
def test_pieces_are_the_whole_file(tmp_path, rng, small_pieces, kind):
    s = random_stream(rng, n=6000, t_max=600_000)
    f = tmp_path / ("e.txt" if kind == "txt" else "e.npz")
    if kind == "txt":
        write_events_text(f, s)
    else:
        write_events_npz(f, s, [Exposure(1000, 2000)], compress=kind.endswith("compressed"))
    with open_events(f) as rec:
        assert rec.num_events() == 6000 and rec.sensor_size() == (40, 30)
        assert len(rec._count) > 5  # really in pieces
        same(rec.events(), s)
        for a in (0, 77_777, 299_999, 555_000):  # windows across piece edges, in any order
            same(rec.events(a, a + 40_000), s.slice(a, a + 40_000))
        same(EventStream.concatenate(list(rec.iter_events(100_000, 500_000, max_events=333))),
             s.slice(100_000, 500_000))
        if kind != "txt":
            assert rec.stored_windows() == [Exposure(1000, 2000)]


def test_a_window_reads_only_its_pieces(tmp_path, rng, small_pieces, monkeypatch):
    """An uncompressed .npz is read where a window lies, not from the start (memory and time:
    one window, however long the recording)."""
    s = random_stream(rng, n=20_000, t_max=2_000_000)
    f = tmp_path / "e.npz"
    write_events_npz(f, s)
    rec = open_events(f)
    read = []
    real = npz.NpzRecording._column
    monkeypatch.setattr(npz.NpzRecording, "_column",
                        lambda self, name, data: read.append(len(data)) or real(self, name, data))
    same(rec.events(1_500_000, 1_510_000), s.slice(1_500_000, 1_510_000))
    assert sum(read) <= 2 * 500 * 13  # at most two chunks of 500 events, 13 bytes each


def test_damaged_bytes_of_a_streamed_npz_are_named(tmp_path, rng, small_pieces):
    s = random_stream(rng, n=3000)
    f = tmp_path / "e.npz"
    write_events_npz(f, s)
    with zipfile.ZipFile(f) as zf:
        info = zf.getinfo("p.npy")
    data = bytearray(f.read_bytes())
    at = info.header_offset + 30 + len(info.filename) + len(info.extra) + 128 + 2000
    data[at] = 5  # a polarity of 5, inside the stored array: the CRC no longer matches
    f.write_bytes(bytes(data))
    with pytest.raises(FormatError, match=r"key 'p' cannot be read, truncated or corrupt "
                                          r"\(Bad CRC-32 for file 'p.npy'\)"):
        open_events(f)


def test_a_bad_value_is_named_with_its_place_in_the_file(tmp_path, small_pieces):
    t = np.arange(3000, dtype=np.int64) * 10
    t[2222] = 5  # back in time, in the fifth chunk
    np.savez(tmp_path / "e.npz", x=np.zeros(3000, np.uint16), y=np.zeros(3000, np.uint16), t=t,
             p=np.ones(3000, np.int8))
    with pytest.raises(InputError, match=r"event times are not sorted \(event 2222 goes back"):
        open_events(tmp_path / "e.npz")
    lines = "".join(f"{i / 1e4:.6f} 1 1 1\n" for i in range(2000))
    (tmp_path / "e.txt").write_text(lines + "0.5 1 1 oops\n")
    with pytest.raises(FormatError, match="malformed event line near line 2001"):
        open_events(tmp_path / "e.txt")


def test_voxelize_of_the_whole_span_in_pieces_is_exact(tmp_path, rng, small_pieces):
    s = random_stream(rng, n=8000, t_max=400_000)
    f = tmp_path / "e.npz"
    write_events_npz(f, s)
    r = CliRunner().invoke(app, ["voxelize", str(f), "-o", str(tmp_path / "v.npz")])
    assert r.exit_code == 0, r.output
    from trmd_cli.voxel import scer_voxels

    win = Exposure(*s.time_range_us)
    with np.load(tmp_path / "v.npz") as z:
        np.testing.assert_array_equal(z["voxels"][0], scer_voxels(s, win, 3))


def test_text_options_still_apply_to_every_piece(tmp_path, small_pieces):
    rows = "".join(f"{i} {i % 5 + 1} {i % 3 + 1} {i % 2}\n" for i in range(3000))
    (tmp_path / "e.txt").write_text("t,y,x,p\n" + rows.replace(" ", ","))
    rec = open_events(tmp_path / "e.txt", ReadOptions(columns=("t", "y", "x", "p"),
                                                      one_based=True, time_unit="ms",
                                                      sensor=(3, 5)))
    s = rec.events()
    assert len(rec._count) > 5
    np.testing.assert_array_equal(s.t, np.arange(3000) * 1000)
    np.testing.assert_array_equal(s.y, np.arange(3000) % 5)
    np.testing.assert_array_equal(s.x, np.arange(3000) % 3)
