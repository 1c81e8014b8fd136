"""jAER AEDAT 2.0 and cAER AEDAT 3.1: files written by the reference writers of
:mod:`tests.helpers.aedat` (built from the published format descriptions, not from the reader)
read back event for event, frame for frame; damaged files are one clear error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers import aedat as A
from tests.helpers.cli import assert_one_error_line
from tests.helpers.data import assert_events, random_events
from trmd_cli.cli.app import app
from trmd_cli.errors import FormatError, InputError
from trmd_cli.events import Exposure
from trmd_cli.read import ReadOptions, detect_format, open_events
from trmd_cli.read import aedat as aedat_mod
from trmd_cli.read import chunked as chunked_mod

runner = CliRunner()


def events(rng, n, width, height, t0=1_000, span=200_000):
    return random_events(rng, n, width, height, t0, span)


@pytest.fixture
def streaming(monkeypatch):
    """Small chunks and nothing kept in memory: the seeking, chunk-by-chunk paths."""
    monkeypatch.setattr(chunked_mod, "CACHE_MAX_EVENTS", 0)
    monkeypatch.setattr(aedat_mod, "AEDAT2_CHUNK_RECORDS", 4096)
    monkeypatch.setattr(aedat_mod, "AEDAT3_CHUNK_EVENTS", 1000)


def davis_file(path: Path, rng, width=240, height=180, chip=A.DAVIS240, n=4000, frames=2,
               extra=()):
    """DVS events and global-shutter APS frames, interleaved by time as a camera writes them."""
    t, x, y, p = events(rng, n, width, height)
    addr = [A.davis_dvs_addresses(x, y, p, width, height)]
    ts = [t]
    shots = []
    for k in range(frames):
        cds = rng.integers(0, 1024, (height, width))
        f = A.ApsFrame(cds, 20_000 + 60_000 * k, 25_000 + 60_000 * k, 45_000 + 60_000 * k)
        a, tt = A.davis_aps_records(f, width, height)
        addr.append(a)
        ts.append(tt)
        shots.append(f)
    for a, tt in extra:
        addr.append(np.asarray(a))
        ts.append(np.asarray(tt))
    path.write_bytes(A.aedat2_bytes(np.concatenate(addr), np.concatenate(ts), chip))
    return (t, x, y, p), shots


# -- AEDAT 2.0 ----------------------------------------------------------------------------------


@pytest.mark.parametrize("chip,size", [(A.DAVIS240, (240, 180)), (A.DAVIS346, (346, 260))])
def test_aedat2_davis_events_and_frames_exact(tmp_path, rng, chip, size):
    path = tmp_path / "rec.aedat"
    (t, x, y, p), shots = davis_file(path, rng, *size, chip=chip)
    assert detect_format(path) == "aedat2"
    with open_events(path) as rec:
        assert (rec.format, rec.width, rec.height) == ("aedat2", *size)
        assert rec.warnings == []
        assert rec.num_events() == len(t)
        assert_events(rec.events(), t, x, y, p)
        frames = list(rec.frames())
        assert len(frames) == len(shots) and rec.num_frames() == len(shots)
        for fr, shot in zip(frames, shots, strict=True):
            # the exposure runs from the last reset read to the first signal read
            assert fr.exposure == Exposure(shot.exposure_start, shot.exposure_end)
            np.testing.assert_array_equal(np.rint(fr.image * 1023).astype(int), shot.cds)
        assert rec.frame_exposures() == [f.exposure for f in frames]


def test_aedat2_streams_in_chunks_and_seeks(tmp_path, rng, streaming):
    """Many chunks (4096 records), frames straddling them, no AEChip line (`sensor` gives the
    size): windows, chunks and frames as when read whole."""
    path = tmp_path / "rec.aedat"
    (t, x, y, p), shots = davis_file(path, rng, 64, 48, chip=None, n=30_000, frames=3)
    with open_events(path, ReadOptions(sensor=(64, 48))) as rec:
        assert (rec.width, rec.height) == (64, 48)
        assert any("`sensor`" in w for w in rec.warnings)
        assert len(rec._first) > 5
        for lo, hi in [(150_000, 160_000), (1_000, 5_000), (90_000, 91_000), (199_000, 10**9)]:
            sel = (t >= lo) & (t < hi)
            assert_events(rec.events(lo, hi), t[sel], x[sel], y[sel], p[sel])
        chunks = list(rec.iter_chunks(max_events=7000))
        assert sum(len(c) for c in chunks) == len(t)
        got = list(rec.frames())
        assert [f.exposure for f in got] == [Exposure(s.exposure_start, s.exposure_end)
                                             for s in shots]
        np.testing.assert_array_equal(np.rint(got[2].image * 1023).astype(int), shots[2].cds)


def test_aedat2_dvs128_layout(tmp_path, rng):
    """DVS128: raw polarity 0 is ON, x mirrored, y counted from the bottom (jAER, libcaer)."""
    t, x, y, p = events(rng, 2000, 128, 128)
    path = tmp_path / "dvs.aedat"
    special_t = np.array([t[10], t[500]])
    a = np.concatenate([A.dvs128_addresses(x, y, p), [0x8000, 0x8000]])
    path.write_bytes(A.aedat2_bytes(a, np.concatenate([t, special_t]), A.DVS128))
    with open_events(path) as rec:
        assert (rec.width, rec.height, rec.num_events()) == (128, 128, len(t))
        assert_events(rec.events(), t, x, y, p)
        assert rec.warnings == ["skipped what trmd does not read: 2 external (special) events"]
        assert list(rec.frames()) == []


def test_aedat2_timestamp_wrap_is_unwrapped(tmp_path):
    """The 32-bit µs counter wraps after 71.6 min: times keep growing past 2**32."""
    t = np.array([2**32 - 300, 2**32 - 20, 2**32 + 5, 2**32 + 900], np.int64)
    x, y, p = np.array([1, 2, 3, 4]), np.array([5, 6, 7, 8]), np.array([1, -1, 1, -1])
    path = tmp_path / "w.aedat"
    path.write_bytes(A.aedat2_bytes(A.davis_dvs_addresses(x, y, p, 240, 180), t))
    with open_events(path) as rec:
        assert_events(rec.events(), t, x, y, p)


def test_aedat2_skips_imu_and_triggers_and_incomplete_frames_with_warnings(tmp_path, rng):
    imu = ([0x80000C00 | (k << 28) for k in range(7)], [30_000] * 7)
    trigger = ([0x400], [31_000])
    path = tmp_path / "rec.aedat"
    (t, x, y, p), shots = davis_file(path, rng, frames=1, extra=[imu, trigger])
    # a second frame cut short: reset reads of half the pixels, then signal reads
    a, ts = A.davis_aps_records(A.ApsFrame(np.zeros((180, 240), int), 150_000, 151_000,
                                           160_000), 240, 180)
    half = np.r_[0:20_000, 43_200:63_200]
    data = path.read_bytes()
    body = np.frombuffer(data[len(A.aedat2_header(A.DAVIS240)):], [("a", ">u4"), ("t", ">u4")])
    path.write_bytes(A.aedat2_bytes(np.concatenate([body["a"], a[half]]),
                                    np.concatenate([body["t"], ts[half]])))
    with open_events(path) as rec:
        assert rec.num_events() == len(t)
        assert len(list(rec.frames())) == 1
        joined = " | ".join(rec.warnings)
        assert "7 IMU samples" in joined and "1 external-input events" in joined
        assert "1 APS frame(s) do not read every pixel once" in joined


def test_aedat2_damage_is_one_clear_error(tmp_path, rng):
    path = tmp_path / "rec.aedat"
    davis_file(path, rng, frames=1)
    cut = tmp_path / "cut.aedat"
    cut.write_bytes(path.read_bytes()[:-3])
    with pytest.raises(FormatError, match=r"partial record .*truncate -s"):
        open_events(cut)
    unknown = tmp_path / "unknown.aedat"
    t, x, y, p = events(rng, 50, 240, 180)
    unknown.write_bytes(A.aedat2_bytes(A.davis_dvs_addresses(x, y, p, 240, 180), t, None))
    with pytest.raises(InputError, match="sensor=") as e:
        open_events(unknown)
    assert e.value.path == str(unknown)
    back = tmp_path / "back.aedat"
    back.write_bytes(A.aedat2_bytes(A.davis_dvs_addresses(x, y, p, 240, 180), t)[:-8]
                     + np.array([(0, 5)], [("a", ">u4"), ("t", ">u4")]).tobytes())
    with pytest.raises(FormatError, match="goes back in time"):
        open_events(back)
    r = runner.invoke(app, ["info", str(cut)])
    assert_one_error_line(r, "cut.aedat", "partial record")
    r = runner.invoke(app, ["convert", str(unknown), "-o", str(tmp_path / "o.h5")])
    assert_one_error_line(r, "unknown.aedat", "--sensor WxH")
    assert not (tmp_path / "o.h5").exists()


# -- AEDAT 3.1 ----------------------------------------------------------------------------------


def aedat3_file(path: Path, rng, n=5000, width=240, height=180, t0=2**31 - 50_000):
    """Polarity packets across a timestamp overflow (t ≥ 2**31), a frame packet, an IMU packet,
    an event marked invalid, and a second source's polarity packet."""
    t, x, y, p = events(rng, n, width, height, t0=t0, span=100_000)
    split = int(np.searchsorted(t, 2**31))
    assert 0 < split < n
    px = rng.integers(0, 65536, (height, width)).astype(np.uint16)
    rgb = rng.integers(0, 65536, (height, width, 3)).astype(np.uint16)
    valid = np.ones(split, bool)
    valid[7] = False
    e0, e1 = (t0 + 10_000, t0 + 30_000), (2**31 + 10_000, 2**31 + 25_000)
    data = (A.aedat3_header("DAVIS240C")
            + A.polarity_packet(x[:split], y[:split], t[:split], p[:split], valid=valid)
            + A.frame_packet(px, e0) + A.imu6_packet(t0 + 11_000)
            + A.polarity_packet(x[:3], y[:3], t[:3], p[:3], source=2)
            + A.polarity_packet(x[split:], y[split:], t[split:], p[split:])
            + A.frame_packet(rgb, e1))
    path.write_bytes(data)
    keep = np.ones(n, bool)
    keep[7] = False
    return (t[keep], x[keep], y[keep], p[keep]), [(px, e0), (rgb, e1)]


def test_aedat3_events_and_frames_exact(tmp_path, rng):
    path = tmp_path / "rec.aedat"
    (t, x, y, p), frames = aedat3_file(path, rng)
    assert detect_format(path) == "aedat3"
    with open_events(path) as rec:
        assert (rec.format, rec.width, rec.height) == ("aedat3", 240, 180)
        assert rec.num_events() == len(t)
        assert_events(rec.events(), t, x, y, p)
        got = list(rec.frames())
        assert [f.exposure for f in got] == [Exposure(*e) for _, e in frames]
        np.testing.assert_array_equal(np.rint(got[0].image * 65535).astype(int), frames[0][0])
        np.testing.assert_array_equal(np.rint(got[1].image * 65535).astype(int), frames[1][0])
        joined = " | ".join(rec.warnings)
        assert "2 IMU6 events (type 3)" in joined
        assert "1 event(s) marked invalid" in joined
        assert "3 polarity events (type 1, source 2)" in joined
        assert "events from 2 sources (1, 2); reading source 1" in joined


def test_aedat3_streams_packets_and_seeks(tmp_path, rng, streaming):
    path = tmp_path / "rec.aedat"
    t, x, y, p = events(rng, 20_000, 240, 180, t0=0, span=1_000_000)
    body = b"".join(A.polarity_packet(x[i:i + 512], y[i:i + 512], t[i:i + 512], p[i:i + 512])
                    + (A.imu6_packet(int(t[i])) if i % 2048 == 0 else b"")
                    for i in range(0, len(t), 512))
    path.write_bytes(A.aedat3_header("DAVIS240C") + body)
    with open_events(path) as rec:
        assert len(rec._first) > 10
        for lo, hi in [(500_000, 510_000), (0, 3_000), (999_000, 2_000_000)]:
            sel = (t >= lo) & (t < hi)
            assert_events(rec.events(lo, hi), t[sel], x[sel], y[sel], p[sel])
        assert_events(rec.events(), t, x, y, p)


def test_aedat3_damage_is_one_clear_error(tmp_path, rng):
    path = tmp_path / "rec.aedat"
    aedat3_file(path, rng)
    data = path.read_bytes()
    head = len(A.aedat3_header("DAVIS240C"))
    for name, damaged, needle in [
        ("cut.aedat", data[:-100], "ends inside a packet of frame events"),
        ("cut-header.aedat", data[:head + 10], "ends inside the header of a packet"),
        ("no-end.aedat", data[:head - 20], "END-HEADER"),
        ("bad-packet.aedat", data[:head + 20] + (10**6).to_bytes(4, "little") + data[head + 24:],
         "impossible header"),
    ]:
        p = tmp_path / name
        p.write_bytes(damaged)
        with pytest.raises(FormatError, match=needle) as e:
            with open_events(p) as rec:
                list(rec.frames())
        assert e.value.path == str(p) and e.value.hint
        r = runner.invoke(app, ["info", str(p)])
        assert_one_error_line(r, name, needle)
    old = tmp_path / "old.aedat"
    old.write_bytes(b"#!AER-DAT3.0\r\n" + data[head:])
    r = runner.invoke(app, ["info", str(old)])
    assert_one_error_line(r, "old.aedat", "not supported")


def test_aedat3_deblur_runs_on_its_frames(tmp_path, rng):
    """`trmd deblur REC.aedat -o OUT/` uses the file's frames and their exposures."""
    W, H = 32, 24
    t, x, y, p = events(rng, 3000, W, H, t0=0, span=100_000)
    img = (rng.random((H, W)) * 40_000 + 10_000).astype(np.uint16)
    path = tmp_path / "rec.aedat"
    path.write_bytes(A.aedat3_header("SomeCamera") + A.polarity_packet(x, y, t, p)
                     + A.frame_packet(img, (20_000, 60_000)))
    out = tmp_path / "out"
    r = runner.invoke(app, ["deblur", str(path), "-o", str(out), "--method", "edi",
                            "--sensor", f"{W}x{H}", "--contrast", "0.2"])
    assert r.exit_code == 0, r.output
    assert (out / "000000" / "sharp.png").is_file()
