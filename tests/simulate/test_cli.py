"""`trmd simulate`: stills, frame folders, videos, training sets, and bad input."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.data import shifted, texture
from trmd_cli.cli.app import app
from trmd_cli.write import write_image

runner = CliRunner()


@pytest.fixture(scope="module")
def still(tmp_path_factory):
    p = tmp_path_factory.mktemp("still") / "tex.png"
    write_image(p, texture(160, 200, seed=2))
    return p


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def test_still_to_h5(tmp_path, still):
    out = tmp_path / "sim.h5"
    r = run("simulate", still, "-o", out, "--size", "64x48", "--count", "2", "--frames", "2",
            "--exposure-ms", "10", "--frame-interval-ms", "15", "--n", "2", "--seed", "3")
    assert r.exit_code == 0, r.output
    with h5py.File(out, "r") as f:
        assert f.attrs["format"] == "trmd" and f.attrs["width"] == 64 and f.attrs["height"] == 48
        g = f["frames"]
        assert g["blurry"].shape == (4, 48, 64)
        assert g["sharp"].shape == (4, 5, 48, 64)
        start, end = g["exposure_start"][:], g["exposure_end"][:]
        np.testing.assert_array_equal(end - start, 10_000)
        assert start[1] - start[0] == 15_000
        assert start[2] > end[1]  # the second sample follows the first on one timeline
        t = f["events"]["t"][:]
        assert len(t) > 100 and np.all(np.diff(t) >= 0)
        c = g["contrast"][:]
        assert np.all((c > 0.2) & (c < 0.3))  # DAVIS-like default 0.25 ± mismatch
        assert "sensor" in f.attrs["simulator"]


def test_clean_flag_and_explicit_contrast(tmp_path, still):
    out = tmp_path / "clean.h5"
    r = run("simulate", still, "-o", out, "--size", "48x40", "--clean", "--contrast", "0.3")
    assert r.exit_code == 0, r.output
    with h5py.File(out, "r") as f:
        assert f["frames"]["contrast"][0] == pytest.approx(0.3)
        p = f["events"]["p"][:]
        assert set(np.unique(p)) <= {-1, 1}
    # the voxelize command reads the file directly
    r = run("voxelize", out, "-o", tmp_path / "v.npz")
    assert r.exit_code == 0, r.output
    assert np.load(tmp_path / "v.npz")["voxels"].shape == (1, 6, 40, 48)


def make_folder(folder, count=5, step=3.0):
    folder.mkdir()
    img = texture(90, 120, seed=5)
    for k in range(count):
        write_image(folder / f"{k:03d}.png", shifted(img, k * step))
    return folder


def test_frame_folder_with_fps(tmp_path):
    folder = make_folder(tmp_path / "frames")
    out = tmp_path / "f.h5"
    r = run("simulate", folder, "-o", out, "--fps", "50", "--size", "60x45", "--clean",
            "--exposure-ms", "30")
    assert r.exit_code == 0, r.output
    with h5py.File(out, "r") as f:
        t = f["events"]["t"][:]
        # the events cover the frames' whole span (0 … 80 ms), not just the exposures
        assert t[0] < 10_000 and t[-1] > 70_000
        assert f["frames"]["blurry"].shape == (2, 45, 60)  # at 0 and 36 ms


def test_a_frame_count_that_does_not_fit_is_said(tmp_path):
    folder = make_folder(tmp_path / "frames")
    r = run("simulate", folder, "-o", tmp_path / "f.h5", "--fps", "50", "--size", "60x45",
            "--clean", "--exposure-ms", "30", "--frames", "50")
    assert r.exit_code == 0, r.output
    assert "--frames 50: only 2 exposure(s) of 30 ms fit in the 80 ms the source spans" in \
        r.output


def test_frame_folder_with_timestamps(tmp_path):
    folder = make_folder(tmp_path / "frames", count=4)
    ts = tmp_path / "ts.txt"
    ts.write_text("1.000\n1.010\n1.030\n1.040\n")
    out = tmp_path / "ts.h5"
    r = run("simulate", folder, "-o", out, "--timestamps", ts, "--size", "60x45",
            "--exposure-ms", "15")
    assert r.exit_code == 0, r.output
    with h5py.File(out, "r") as f:
        assert f["frames"]["exposure_start"][0] == 1_000_000


def test_video_file(tmp_path):
    import cv2

    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (120, 90))
    if not writer.isOpened():
        pytest.skip("OpenCV cannot write MJPG here")
    img = texture(90, 120, seed=6)
    for k in range(6):
        frame = (np.clip(shifted(img, 2.0 * k), 0, 1) * 255).astype(np.uint8)
        writer.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
    writer.release()
    out = tmp_path / "v.h5"
    r = run("simulate", path, "-o", out, "--size", "60x45", "--clean")
    assert r.exit_code == 0, r.output
    with h5py.File(out, "r") as f:
        # 25 fps → default exposure of 3 frame intervals (120 ms) in a 200 ms clip
        assert f["frames"]["exposure_end"][0] - f["frames"]["exposure_start"][0] == 120_000
        assert f["events"]["t"][-1] > 150_000


def test_training_set(tmp_path, still):
    out = tmp_path / "train.h5"
    r = run("simulate", still, "-o", out, "--training-set", "--count", "3", "--crop", "32",
            "--n", "1")
    assert r.exit_code == 0, r.output
    from trmd_cli.simulate.dataset import H5SampleDataset

    ds = H5SampleDataset(out)
    assert len(ds) == 3 and ds[2]["sharp"].shape == (3, 1, 32, 32)


def test_training_set_flags_pin_their_values(tmp_path, still):
    out = tmp_path / "train.h5"
    r = run("simulate", still, "-o", out, "--training-set", "--count", "4", "--crop", "32",
            "--n", "1", "--contrast", "0.3", "--exposure-ms", "15", "--shot-noise", "0",
            "--motion-px", "5")
    assert r.exit_code == 0, r.output
    with h5py.File(out, "r") as f:
        g = f["frames"]
        # recorded: the mean over the pixels' thresholds (mismatch σ ≤ 0.06 is still drawn)
        np.testing.assert_allclose(g["contrast"][:], 0.3, atol=0.005)
        np.testing.assert_array_equal(g["exposure_end"][:] - g["exposure_start"][:], 15_000)
    # the default ranges really vary (the test above would pass vacuously otherwise)
    out2 = tmp_path / "free.h5"
    assert run("simulate", still, "-o", out2, "--training-set", "--count", "4", "--crop", "32",
               "--n", "1").exit_code == 0
    with h5py.File(out2, "r") as f:
        assert np.ptp(f["frames"]["contrast"][:]) > 0.01
        assert np.ptp(f["frames"]["exposure_end"][:] - f["frames"]["exposure_start"][:]) > 0


def test_training_set_options_mapping():
    from trmd_cli.cli.simulate import training_set_options

    assert training_set_options() == {}
    o = training_set_options(clean=True, contrast=0.2)
    assert o["sensor_ranges"]["clean_prob"] == 1.0 and o["sensor_ranges"]["contrast"] == (0.2, 0.2)
    assert o["read_noise"] == (0.0, 0.0)
    o = training_set_options(leak=0.5, layers=0, motion_px=12)
    assert o["sensor_ranges"]["leak_hz"] == (0.5, 0.5) and o["sensor_ranges"]["clean_prob"] == 0
    assert o["motion"]["translation_px"] == 12 and o["motion"]["foreground_prob"] == 0
    assert o["sensor_ranges"]["contrast"] == (0.1, 0.5)  # not given: the training range


@pytest.mark.parametrize("args, message", [
    (["missing.png"], "not found"),
    (["{still}", "--training-set", "--clean", "--leak", "1"], "--clean with --leak"),
    (["{folder}"], "needs its frame times"),
    (["{folder}", "--fps", "50", "--exposure-ms", "500"], "does not fit"),
    (["{still}", "--size", "abc"], "not WxH"),
    (["{folder}", "--timestamps", "{bad_ts}"], "timestamps for 5 frames"),
    # numbers the simulator cannot use are named by their option, never an internal error
    (["{still}", "--exposure-ms", "nan"], "--exposure-ms must be a finite number"),
    (["{still}", "--exposure-ms", "inf"], "--exposure-ms must be a finite number"),
    (["{still}", "--exposure-ms", "0.0001"], "at least 0.002 ms"),
    (["{still}", "--seed", "-1"], "--seed must be 0 or more"),
    (["{still}", "--read-noise", "inf"], "--read-noise must be a finite number"),
    (["{still}", "--motion-px", "inf"], "--motion-px must be a finite number"),
    (["{folder}", "--fps", "nan"], "--fps must be a positive finite number"),
    (["{still}", "--size", "0x48"], "--size '0x48' is not WxH"),
    (["{still}", "--size", "8x8"], "outside 16x16"),
    (["{still}", "--size", "100000x100000"], "outside 16x16"),
    (["{folder}", "--timestamps", "{us_ts}"], "are the times in ms or µs"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, still, args, message):
    folder = make_folder(tmp_path / "frames")
    bad_ts = tmp_path / "bad.txt"
    bad_ts.write_text("0\n0.1\n")
    us_ts = tmp_path / "us.txt"
    us_ts.write_text("".join(f"{33_000 * k}\n" for k in range(5)))
    out = tmp_path / "out.h5"
    args = [a.format(folder=folder, still=still, bad_ts=bad_ts, us_ts=us_ts) for a in args]
    if args[0] == "missing.png":
        args[0] = str(tmp_path / "missing.png")
    r = run("simulate", *args, "-o", out)
    assert r.exit_code == 2, r.output
    assert message in r.output
    assert "Traceback" not in r.output
    assert not out.exists()
    assert not list(tmp_path.glob(".out*"))  # no temporary file left behind


def test_existing_output_needs_overwrite(tmp_path, still):
    out = tmp_path / "x.h5"
    out.write_bytes(b"keep")
    r = run("simulate", still, "-o", out, "--size", "32x32")
    assert r.exit_code == 2 and "--overwrite" in r.output
    assert out.read_bytes() == b"keep"
    r = run("simulate", still, "-o", out, "--size", "32x32", "--overwrite")
    assert r.exit_code == 0, r.output
    assert out.read_bytes()[:4] == b"\x89HDF"


def test_flags_one_kind_of_simulation_ignores_are_said(tmp_path, still):
    r = run("simulate", still, "-o", tmp_path / "t.h5", "--training-set", "--count", "1",
            "--crop", "32", "--size", "64x48", "--frames", "3")
    assert r.exit_code == 0, r.output
    assert "--size is ignored" in r.output and "--frames is ignored" in r.output
    r = run("simulate", still, "-o", tmp_path / "s.h5", "--size", "64x48", "--crop", "32")
    assert r.exit_code == 0 and "--crop is ignored" in r.output, r.output
