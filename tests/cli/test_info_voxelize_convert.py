"""`trmd --version/--help`, info, voxelize, convert through the CLI: outputs and error lines."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.data import random_stream
from trmd_cli import __version__
from trmd_cli.cli.app import app
from trmd_cli.events import Exposure
from trmd_cli.read import open_events
from trmd_cli.voxel import scer_voxels
from trmd_cli.write import write_events_npz

runner = CliRunner()


@pytest.fixture
def npz(tmp_path, rng):
    s = random_stream(rng, n=20_000)
    path = tmp_path / "events.npz"
    write_events_npz(path, s, [Exposure(0, 40_000), Exposure(50_000, 90_000)])
    return path, s


def test_version_and_help_without_torch():
    r = runner.invoke(app, ["--version"])
    assert r.exit_code == 0 and __version__ in r.stdout
    # `trmd --help` must not import torch (instant start)
    code = ("import sys; from trmd_cli.cli.app import app; "
            "from typer.testing import CliRunner; CliRunner().invoke(app, ['--help']); "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_info_json(npz):
    path, s = npz
    r = runner.invoke(app, ["info", str(path), "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert d["events"] == len(s) and d["sensor"] == "40x30"
    assert d["on_fraction"] == pytest.approx(float(np.mean(s.p > 0)), abs=1e-4)
    assert [f["events"] for f in d["frames"]] == [
        len(s.slice(0, 40_001)), len(s.slice(50_000, 90_001))]


def test_voxelize_matches_library(npz, tmp_path):
    path, s = npz
    out = tmp_path / "v.npz"
    r = runner.invoke(app, ["voxelize", str(path), "-o", str(out), "--n", "2",
                            "--preview", str(tmp_path / "v.png")])
    assert r.exit_code == 0, r.output
    with np.load(out) as z:
        assert z["voxels"].shape == (2, 4, 30, 40)
        np.testing.assert_array_equal(z["voxels"][1], scer_voxels(s, Exposure(50_000, 90_000), 2))
        assert z["exposure"].tolist() == [[0, 40_000], [50_000, 90_000]]
    assert (tmp_path / "v.png").stat().st_size > 0


def test_voxelize_explicit_exposure_in_seconds(npz, tmp_path):
    path, s = npz
    out = tmp_path / "v.npz"
    r = runner.invoke(app, ["voxelize", str(path), "-o", str(out), "--exposure", "0.01", "0.02"])
    assert r.exit_code == 0, r.output
    with np.load(out) as z:
        assert z["exposure"].tolist() == [[10_000, 20_000]]
        np.testing.assert_array_equal(z["voxels"][0], scer_voxels(s, Exposure(10_000, 20_000), 3))


def test_convert_round_trips(npz, tmp_path):
    path, s = npz
    for ext in ("h5", "txt", "npz"):
        out = tmp_path / f"c.{ext}"
        r = runner.invoke(app, ["convert", str(path), "-o", str(out)])
        assert r.exit_code == 0, r.output
        got = open_events(out).events()
        for k in "xytp":
            np.testing.assert_array_equal(getattr(got, k), getattr(s, k))


@pytest.mark.parametrize("args,needle", [
    (["info", "missing.npz"], "file not found"),
    (["voxelize", "{npz}", "-o", "{tmp}/v.npz", "--exposure", "200000", "300000"],
     "outside the events"),
    (["voxelize", "{npz}", "-o", "{tmp}/v.npz", "--exposure", "6", "5"], "empty or reversed"),
    (["voxelize", "{npz}", "-o", "{tmp}/v.npz", "--sensor", "10"], "not WxH"),
    (["voxelize", "{npz}", "-o", "{tmp}/v.npz", "--sensor", "10x10"], "outside the sensor"),
    (["info", "{npz}", "--time-unit", "days"], "--time-unit"),
    (["convert", "{npz}", "-o", "{tmp}/x.png"], "unknown output type"),
    # the picture's type is checked before the voxels are written, and named as given
    (["voxelize", "{npz}", "-o", "{tmp}/v.npz", "--preview", "{tmp}/p.txt"],
     "p.txt: cannot write a .txt picture"),
])
def test_bad_input_one_line_exit_2(npz, tmp_path, args, needle):
    path, _ = npz
    args = [a.format(npz=path, tmp=tmp_path) for a in args]
    r = runner.invoke(app, args)
    assert r.exit_code == 2, r.output
    assert needle in r.output
    assert "Traceback" not in r.output
    assert not (tmp_path / "v.npz").exists()


def test_existing_output_refused_then_overwritten(npz, tmp_path):
    path, _ = npz
    out = tmp_path / "v.npz"
    out.write_bytes(b"keep me")
    r = runner.invoke(app, ["voxelize", str(path), "-o", str(out)])
    assert r.exit_code == 2 and "--overwrite" in r.output
    assert out.read_bytes() == b"keep me"
    r = runner.invoke(app, ["voxelize", str(path), "-o", str(out), "--overwrite"])
    assert r.exit_code == 0
    assert not [p for p in tmp_path.iterdir() if ".tmp" in p.name]


def test_info_describes_weights(tmp_path):
    import torch

    from trmd_cli.models import count_params, create_model
    from trmd_cli.models.weights import describe_weights, save_weights

    torch.manual_seed(0)
    plain = save_weights(tmp_path / "plain.safetensors", create_model("test_trmd"), half=False)
    timed = save_weights(tmp_path / "timed.safetensors",
                         create_model("test_trmd", prior="edi_c", timing=True), half=True,
                         meta={"validation": {"trmd": {"psnr_mid": 30.123, "psnr_seq": 28.5},
                                              "set": "a test set"}})
    d = describe_weights(plain)
    assert d["architecture"] == "test_trmd" and d["inputs"] == [] and d["n"] == 3
    assert d["parameters"] == count_params(create_model("test_trmd"))
    d = describe_weights(timed)
    assert d["dtype"] == "float16" and len(d["inputs"]) == 2
    assert d["parameters"] == count_params(create_model("test_trmd", prior="edi_c", timing=True))
    r = runner.invoke(app, ["info", str(timed), "--json"])
    assert r.exit_code == 0 and json.loads(r.stdout)["validation"]["trmd"]["psnr_mid"] == 30.123
    r = runner.invoke(app, ["info", str(timed)])
    assert r.exit_code == 0 and "timing" in r.stdout and "30.12 / 28.50" in r.stdout
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not weights")
    r = runner.invoke(app, ["info", str(bad)])
    assert r.exit_code == 2 and "Traceback" not in r.output


@pytest.mark.parametrize("source", ["mat", "npz"])
def test_convert_to_h5_keeps_windows_stored_without_frames(tmp_path, rng, source):
    """A .mat (eSL-Net start/end_timestamp) or .npz window survives the trip to HDF5 and back,
    to the microsecond, and `trmd info` of the result lists it."""
    s = random_stream(rng)
    if source == "mat":
        sio = pytest.importorskip("scipy.io")
        src = tmp_path / "ev.mat"
        sio.savemat(src, {"section_event_timestamp": s.t[None] / 1e6,
                          "section_event_x": s.x[None].astype(np.int64),
                          "section_event_y": s.y[None].astype(np.int64),
                          "section_event_polarity": (s.p[None] > 0).astype(np.int64),
                          "start_timestamp": np.array([[0.010]]),
                          "end_timestamp": np.array([[0.090]])})
        want = [Exposure(10_000, 90_000)]
    else:
        src = tmp_path / "ev.npz"
        want = [Exposure(1_000, 40_000), Exposure(50_000, 90_000)]
        write_events_npz(src, s, want)
    out = tmp_path / "ev.h5"
    r = runner.invoke(app, ["convert", str(src), "-o", str(out), "--sensor", "40x30"])
    assert r.exit_code == 0, r.output
    from trmd_cli.read import ReadOptions
    from trmd_cli.summary import summarize

    with open_events(src, ReadOptions(sensor=(40, 30))) as a, open_events(out) as b:
        assert b.stored_windows() == want == a.stored_windows()
        np.testing.assert_array_equal(a.events().t, b.events().t)
        sa, sb = summarize(a), summarize(b)
        assert sb["exposure_source"] == sa["exposure_source"] == "windows"
        assert [(f["start_us"], f["end_us"], f["events"]) for f in sb["frames"]] == \
            [(f["start_us"], f["end_us"], f["events"]) for f in sa["frames"]]


def test_convert_says_what_the_target_does_not_keep(tmp_path, rng):
    """The simulator's ground truth does not travel through convert, and frames do not fit an
    .npz: both are said, not dropped unsaid."""
    from trmd_cli.write import write_h5

    s = random_stream(rng)
    frames = np.full((1, s.height, s.width), 0.5, np.float32)
    src = write_h5(tmp_path / "sim.h5", s, blurry=frames, exposures=[Exposure(1_000, 40_000)],
                   sharp=np.repeat(frames[:, None], 3, axis=1))
    r = runner.invoke(app, ["convert", str(src), "-o", str(tmp_path / "copy.h5")])
    assert r.exit_code == 0 and "ground truth" in r.output and "not converted" in r.output
    r = runner.invoke(app, ["convert", str(src), "-o", str(tmp_path / "ev.npz")])
    assert r.exit_code == 0 and "the 1 frame(s) are dropped" in r.output
    plain = write_h5(tmp_path / "plain.h5", s)
    r = runner.invoke(app, ["convert", str(plain), "-o", str(tmp_path / "plain2.h5")])
    assert r.exit_code == 0 and "warning" not in r.output


def test_info_describes_a_bins_file(tmp_path):
    counts = np.zeros((6, 8, 10), np.int16)
    counts[0, 1, 2], counts[3, 4, 5] = 3, -2
    np.savez(tmp_path / "bins.npz", event_bins=counts)
    r = runner.invoke(app, ["info", str(tmp_path / "bins.npz"), "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert d["shape"] == [6, 8, 10] and d["sensor"] == "10x8" and d["abs_count"] == 5
