"""`trmd hfr` and the continuous stream (hfr.hfr_stream): frame counts and timing, gaps
filled from the events (checked against ground truth), videos, TRMD with in-between instants."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from trmd_cli.cli.app import app
from trmd_cli.deblur import deblur_frames, exposure_instants
from trmd_cli.events import Exposure
from trmd_cli.hfr import hfr_stream
from trmd_cli.methods import EdiMethod
from trmd_cli.read.frames import read_image
from trmd_cli.read.inputs import open_inputs
from trmd_cli.write import write_h5, write_image

runner = CliRunner()
W, H = 128, 96
T = 20_000


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((np.clip(a, 0, 1) - b) ** 2)))


def scene() -> np.ndarray:
    yy, xx = np.mgrid[0:300, 0:300]
    img = 0.15 + 0.7 * ((xx // 20 + yy // 28) % 2)
    return (img + 0.1 * np.sin(xx / 6.0) * np.cos(yy / 9.0)).astype(np.float32)


@pytest.fixture(scope="module")
def seq():
    """Three back-to-back exposures (no gaps) of one camera path, clean sensor, c = 0.2."""
    from trmd_cli.simulate import SensorConfig, make_sequence

    return make_sequence(scene(), n=3, size=(W, H), exposure_us=T, frames=3,
                         frame_interval_us=T, rng=np.random.default_rng(11),
                         sensor=SensorConfig.clean(0.2))


@pytest.fixture
def gapped(tmp_path, seq):
    """The first and last exposures only, with every event: the middle one becomes a gap."""
    path = tmp_path / "rec.h5"
    write_h5(path, seq.events, blurry=seq.blurry[[0, 2]], exposures=[seq.exposures[0],
                                                                     seq.exposures[2]])
    return path


def test_gap_is_filled_from_the_events(gapped, seq):
    with open_inputs([gapped]) as ins:
        results = deblur_frames(ins.source, EdiMethod(3, 0.2))
        frames = list(hfr_stream(results, ins.source.recording))
    times = np.array([f.t_us for f in frames])
    kinds = [f.kind for f in frames]
    # 7 + 5 gap frames (step T/6 across a gap of T) + 7; evenly spaced, in time order
    assert kinds == ["exposure"] * 7 + ["gap"] * 5 + ["exposure"] * 7
    np.testing.assert_allclose(np.diff(times), T / 6, rtol=1e-6)
    # the gap frames sit at the middle exposure's latent instants k = 1..5: compare with truth
    gap = [f.image for f in frames if f.kind == "gap"]
    for k, img in enumerate(gap, start=1):
        truth = seq.sharp[1, k]
        assert psnr(img, truth) > psnr(seq.blurry[1], truth) + 3, k
        # better than a plain cross-fade between the neighbouring exposures' end frames
        w = k / 6
        fade = (1 - w) * frames[6].image + w * frames[12].image
        assert psnr(img, truth) > psnr(fade, truth) + 1, k


def test_no_events_in_the_gap_gives_a_cross_fade():
    from trmd_cli.deblur import FrameResult
    from trmd_cli.methods import Estimate

    def result(name, e, value):
        inst = exposure_instants(e, 3)
        frames = np.full((3, 4, 5), value, np.float32)
        return FrameResult(0, name, frames[0], e, Estimate(frames, inst, 0.2), 10)

    a, b = result("a", Exposure(0, 600), 0.2), result("b", Exposure(1200, 1800), 0.8)
    out = list(hfr_stream([a, b], recording=None))
    gap = [f for f in out if f.kind == "gap"]
    assert len(gap) == 1 and gap[0].t_us == pytest.approx(900)
    np.testing.assert_allclose(gap[0].image, 0.5, atol=1e-6)


def test_cli_folder_output_and_counts(gapped, tmp_path):
    out = tmp_path / "frames"
    r = runner.invoke(app, ["hfr", str(gapped), "-o", str(out), "--contrast", "0.2",
                            "--per-exposure", "4"])
    assert r.exit_code == 0, r.output
    lines = [ln.split() for ln in (out / "timestamps.txt").read_text().splitlines()
             if not ln.startswith("#")]
    # step T/3 per exposure; gap of T → floor(3 − 0.5) = 2 frames
    assert [ln[2] for ln in lines] == ["exposure"] * 4 + ["gap"] * 2 + ["exposure"] * 4
    assert len(list(out.glob("*.png"))) == 10
    meta = json.loads((out / "meta.json").read_text())
    assert meta["frames"] == {"exposure": 8, "gap": 2} and meta["per_exposure"] == 4
    assert read_image(out / "000000.png").shape == (H, W)


@pytest.mark.parametrize("suffix", [".mp4", ".gif"])
def test_cli_video(gapped, tmp_path, suffix):
    import imageio.v3 as iio

    out = tmp_path / f"slowmo{suffix}"
    r = runner.invoke(app, ["hfr", str(gapped), "-o", str(out), "--fps", "24",
                            "--no-fill-gaps"])
    assert r.exit_code == 0, r.output
    assert "14 frames" in r.stdout
    video = iio.imread(out)
    assert video.shape[0] == 14 and video.shape[1:3] == (H, W)


def test_cli_images_and_events(seq, tmp_path):
    from trmd_cli.write import write_events_npz

    names = []
    for k in range(3):
        names.append(tmp_path / f"{k:04d}.png")
        write_image(names[-1], seq.blurry[k], 16)
    write_events_npz(tmp_path / "ev.npz", seq.events, seq.exposures)
    r = runner.invoke(app, ["hfr", *map(str, names), str(tmp_path / "ev.npz"),
                            "-o", str(tmp_path / "o"), "--contrast", "0.2"])
    assert r.exit_code == 0, r.output
    # back-to-back exposures: no room for gap frames
    assert len(list((tmp_path / "o").glob("*.png"))) == 21


def test_trmd_in_between_instants_are_propagated(gapped, tmp_path):
    from trmd_cli.models import create_model
    from trmd_cli.models.weights import save_weights

    w = save_weights(tmp_path / "w.safetensors", create_model("test_trmd", n=2), meta={})
    out = tmp_path / "o"
    r = runner.invoke(app, ["hfr", str(gapped), "-o", str(out), "--method", "trmd",
                            "--weights", str(w), "--per-exposure", "9", "--threads", "1",
                            "--contrast", "0.2"])
    assert r.exit_code == 0, r.output
    meta = json.loads((out / "meta.json").read_text())
    assert meta["method"] == "trmd" and meta["n"] == 2 and meta["frames"]["exposure"] == 18
    # its own 2N+1 frames; the gap (T, step T/4 → 3 frames) still filled with an estimated c
    r = runner.invoke(app, ["hfr", str(gapped), "-o", str(tmp_path / "o2"), "--method", "trmd",
                            "--weights", str(w), "--threads", "1"])
    assert r.exit_code == 0, r.output
    meta = json.loads((tmp_path / "o2" / "meta.json").read_text())
    assert meta["frames"] == {"exposure": 10, "gap": 3} and len(meta["contrast"]) == 2


def test_frames_out_of_time_order_is_bad_input(seq, tmp_path):
    path = tmp_path / "rev.h5"
    write_h5(path, seq.events, blurry=seq.blurry[[2, 0]],
             exposures=[seq.exposures[2], seq.exposures[0]])
    out = tmp_path / "o.mp4"
    r = runner.invoke(app, ["hfr", str(path), "-o", str(out)])
    assert r.exit_code == 2 and "time order" in r.output
    assert not out.exists()


# --------------------------------------------------------------------------------------------
# binned events: the exposures' frames in order, no event times, no gap filling


@pytest.fixture
def binned_seq(tmp_path, seq):
    """The three exposures as a frames folder and a .mat of 18 bins each (flat)."""
    from tests.helpers.bins import write_bins
    from trmd_cli.voxel import event_bins

    (tmp_path / "blurry").mkdir()
    for k in range(3):
        write_image(tmp_path / "blurry" / f"{k + 1:04d}.png", seq.blurry[k], 16)
    counts = np.concatenate([event_bins(seq.events, e, 18) for e in seq.exposures])
    return tmp_path / "blurry", write_bins(tmp_path / "EventBin.mat", counts.astype(np.int16))


def test_binned_hfr_folder_of_pngs_with_fractions(binned_seq, seq, tmp_path):
    images, bins = binned_seq
    out = tmp_path / "frames"
    r = runner.invoke(app, ["hfr", str(images), str(bins), "-o", str(out), "--method", "edi",
                            "--contrast", "0.2"])
    assert r.exit_code == 0, r.output
    said = [ln for ln in r.stderr.splitlines() if "binned events" in ln]
    assert len(said) == 1 and "gap filling need event times" in said[0]
    assert "21 frames (21 from exposures, 0 filling gaps)" in r.stdout
    lines = (out / "timestamps.txt").read_text().splitlines()
    assert lines[0].startswith("# file fraction kind source")
    rows = [ln.split() for ln in lines[1:]]
    assert [row[0] for row in rows] == [f"{i:06d}.png" for i in range(21)]
    grid = np.linspace(0, 1, 7).tolist()
    assert [float(row[1]) for row in rows] == grid * 3  # evenly spaced within each exposure
    assert {row[2] for row in rows} == {"exposure"}
    assert [row[3] for row in rows] == ["0001"] * 7 + ["0002"] * 7 + ["0003"] * 7
    meta = json.loads((out / "meta.json").read_text())
    assert meta["binned"] is True and meta["fill_gaps"] is False and "time_offset_us" not in meta
    assert meta["frames"] == {"exposure": 21, "gap": 0} and meta["bins_per_frame"] == 18
    # the stream's frames are each exposure's latent frames, in order: against the truth
    for k in range(3):
        for j in (1, 3, 5):
            img = read_image(out / f"{7 * k + j:06d}.png")
            assert psnr(img, seq.sharp[k, j]) > psnr(seq.blurry[k], seq.sharp[k, j]) + 3, (k, j)


@pytest.mark.parametrize("args", [["--per-exposure", "9"], ["--time-offset", "5ms"]])
def test_binned_hfr_options_that_need_event_times(binned_seq, tmp_path, args):
    images, bins = binned_seq
    out = tmp_path / "o.gif"
    r = runner.invoke(app, ["hfr", str(images), str(bins), "-o", str(out), "--method", "edi",
                            "--contrast", "0.2", *args])
    assert r.exit_code == 2, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and args[0] in lines[0], r.output
    assert not out.exists() and not [p for p in tmp_path.iterdir() if ".tmp" in p.name]


def test_binned_hfr_video(binned_seq, tmp_path):
    import imageio.v3 as iio

    images, bins = binned_seq
    out = tmp_path / "slowmo.gif"
    r = runner.invoke(app, ["hfr", str(images), str(bins), "-o", str(out), "--method", "edi",
                            "--contrast", "0.2", "--n", "2", "--per-exposure", "5"])
    assert r.exit_code == 0, r.output
    assert iio.imread(out).shape[0] == 15


def test_meta_gives_every_exposures_c_by_name_and_says_which_took_the_default(seq, tmp_path):
    """One exposure without events (passed through: no c), one with too few to estimate c
    from (the default), one with all of them: meta.json keeps one entry per exposure, names
    them, and lists the default; the run's line does not call a default estimated."""
    from trmd_cli.events import Exposure

    e = seq.exposures
    ev = seq.events
    second = np.flatnonzero((ev.t >= e[1].start_us) & (ev.t <= e[1].end_us))
    few = second[::len(second) // 1000 + 1]  # about a thousand events over the exposure
    keep = np.concatenate([few, np.flatnonzero(ev.t > e[1].end_us)])
    assert 0 < len(few) < 2_000
    path = write_h5(tmp_path / "r.h5", ev.take(keep), blurry=seq.blurry,
                    exposures=[Exposure(e[0].start_us - 30_000, e[0].start_us - 25_000),
                               e[1], e[2]])
    out = tmp_path / "o"
    r = runner.invoke(app, ["hfr", str(path), "-o", str(out), "--method", "edi",
                            "--contrast", "frame", "--no-fill-gaps"])
    assert r.exit_code == 0, r.output
    meta = json.loads((out / "meta.json").read_text())
    assert meta["contrast_frames"] == [f"r.h5#frame{k}" for k in range(3)]
    c = meta["contrast"]
    assert c[0] is None and c[1] == 0.25 and 0.05 < c[2] < 1 and c[2] != 0.25
    assert meta["contrast_defaults"] == ["r.h5#frame1"]
    assert "estimated; 1 of 2 exposures took the default" in r.output


def test_a_run_in_one_process_discards_an_unfinished_runs_stage(gapped, tmp_path):
    out = tmp_path / "frames"
    stage = tmp_path / ".frames.trmd-partial"
    (stage / "done").mkdir(parents=True)
    r = runner.invoke(app, ["hfr", str(gapped), "-o", str(out), "--contrast", "0.2",
                            "--jobs", "1"])
    assert r.exit_code == 0, r.output
    assert "an unfinished run of" in r.output and "is discarded" in r.output
    assert not stage.exists() and out.is_dir()


def test_gap_times_are_written_exactly_on_an_epoch_clock():
    from trmd_cli.hfr import Edge, gap_frames, timestamp_row

    img = np.zeros((4, 4), np.float32)
    t0 = 1_468_941_032_229_165  # an exposure's end, µs since the epoch
    a = Edge("a", img, img, t0 - 6_000.0, float(t0), 7, 6_000, 0.2)
    b = Edge("b", img, img, float(t0 + 4_000), float(t0 + 10_000), 7, 6_000, 0.2)
    frames, _ = gap_frames(a, b)
    # a step of 1 ms (6 ms over 6 steps): floor(4 − 0.5) = 3 frames, the 4 ms gap in 4 parts
    assert [timestamp_row(f).split()[0] for f in frames] == [
        str(t0 + 1000), str(t0 + 2000), str(t0 + 3000)]
    b3 = Edge("b", img, img, float(t0 + 3_500), float(t0 + 9_500), 7, 6_000, 0.2)
    frames, _ = gap_frames(a, b3)  # 3 frames, the 3.5 ms gap in 4 parts
    assert [timestamp_row(f).split()[0] for f in frames] == [
        f"{t0 + 875}", f"{t0 + 1750}", f"{t0 + 2625}"]
    b7 = Edge("b", img, img, float(t0 + 3_000), float(t0 + 9_000), 7, 6_000, 0.2)
    frames, _ = gap_frames(a, b7)  # 2 frames, the 3 ms gap in 3 parts
    assert [timestamp_row(f).split()[0] for f in frames] == [f"{t0 + 1000}", f"{t0 + 2000}"]
    b_odd = Edge("b", img, img, float(t0 + 3_001), float(t0 + 9_001), 7, 6_000, 0.2)
    frames, _ = gap_frames(a, b_odd)  # thirds of 3001 µs: 1000.333 and 2000.667
    assert [timestamp_row(f).split()[0] for f in frames] == [
        f"{t0 + 1000}.333", f"{t0 + 2000}.667"]
