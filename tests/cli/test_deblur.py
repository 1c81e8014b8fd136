"""`trmd deblur` end to end: single frame, recording, paired folders, options, bad input, and the
real recordings (esl-cups every frame sharper; ledvdi bins path sharper)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.data import SHARED, needs_shared
from trmd_cli.cli.app import app
from trmd_cli.events import EventStream, Exposure
from trmd_cli.read.frames import read_image
from trmd_cli.write import write_events_npz, write_h5, write_image

runner = CliRunner()
W, H = 128, 96


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((np.clip(a, 0, 1) - b) ** 2)))


def sharpness(img: np.ndarray) -> float:
    """Variance of the Laplacian: higher = more fine detail."""
    import cv2

    return float(cv2.Laplacian(np.asarray(img, np.float32), cv2.CV_32F).var())


def checker(size: int = 256) -> np.ndarray:
    yy, xx = np.mgrid[0:size, 0:size]
    img = 0.15 + 0.7 * ((xx // 24 + yy // 24) % 2)
    return (img + 0.1 * np.sin(xx / 7.0) * np.cos(yy / 5.0)).astype(np.float32)


@pytest.fixture(scope="module")
def sample():
    from trmd_cli.simulate import SensorConfig, make_sample

    return make_sample(checker(), size=(W, H), rng=np.random.default_rng(5),
                       sensor=SensorConfig.clean(0.2))


@pytest.fixture
def pair(tmp_path, sample):
    img = tmp_path / "blurry.png"
    write_image(img, sample.blurry, 16)
    ev = tmp_path / "events.npz"
    write_events_npz(ev, sample.events, [sample.exposure])
    return img, ev


def run(*args):
    """`trmd deblur` with EDI unless the test picks a method (these tests are about EDI)."""
    args = [str(a) for a in args]
    if "--method" not in args and "--weights" not in args:
        args += ["--method", "edi"]
    return runner.invoke(app, ["deblur", *args])


def test_single_frame_outputs_and_quality(pair, sample, tmp_path):
    img, ev = pair
    out = tmp_path / "out"
    r = run(img, ev, "-o", out, "--compare", "--contrast", "0.2")
    assert r.exit_code == 0, r.output
    names = sorted(p.name for p in out.iterdir())
    assert names == ["compare.png", "frame_000.png", "frame_001.png", "frame_002.png",
                     "frame_003.png", "frame_004.png", "frame_005.png", "frame_006.png",
                     "meta.json", "sharp.png", "timestamps.txt"]
    meta = json.loads((out / "meta.json").read_text())
    assert meta["method"] == "edi" and meta["n"] == 3 and meta["contrast"] == 0.2
    assert meta["weights_hash"] is None and meta["inputs"] == [str(img), str(ev)]
    times = [float(line.split()[1]) for line in (out / "timestamps.txt").read_text().splitlines()
             if not line.startswith("#")]
    np.testing.assert_allclose(times, sample.exposure.instants_us(3), atol=1e-3)
    sharp = read_image(out / "sharp.png")
    np.testing.assert_array_equal(sharp, read_image(out / "frame_003.png"))
    assert psnr(sharp, sample.sharp[3]) > psnr(sample.blurry, sample.sharp[3]) + 4
    assert read_image(out / "compare.png").shape[1] == 2 * W + 4


def test_auto_contrast_is_printed_and_recorded(pair, tmp_path):
    img, ev = pair
    r = run(img, ev, "-o", tmp_path / "o")
    assert r.exit_code == 0, r.output
    meta = json.loads((tmp_path / "o" / "meta.json").read_text())
    assert meta["contrast_estimated"] and f"c = {meta['contrast']:.3f}" in r.stdout
    assert 0.1 < meta["contrast"] < 0.4


def test_n_video_and_16_bit(pair, tmp_path):
    import imageio.v3 as iio

    img, ev = pair
    out, vid = tmp_path / "o", tmp_path / "v.gif"
    r = run(img, ev, "-o", out, "--n", "2", "--video", vid, "--bit-depth", "16",
            "--contrast", "0.2")
    assert r.exit_code == 0, r.output
    assert len(list(out.glob("frame_*.png"))) == 5
    assert iio.imread(vid).shape[0] == 5
    import cv2

    assert cv2.imread(str(out / "sharp.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16


def test_colour_blurry_frame_with_mono_events(sample, tmp_path):
    rgb = np.stack([sample.blurry, 0.8 * sample.blurry, 0.6 * sample.blurry], axis=-1)
    write_image(tmp_path / "rgb.png", rgb, 16)
    write_events_npz(tmp_path / "e.npz", sample.events, [sample.exposure])
    r = run(tmp_path / "rgb.png", tmp_path / "e.npz", "-o", tmp_path / "o", "--contrast", "0.2")
    assert r.exit_code == 0, r.output
    out = read_image(tmp_path / "o" / "sharp.png")
    assert out.shape == (H, W, 3)
    # same event ratio per channel: the channel ratios of the input survive
    bright = out[..., 0] > 0.2
    np.testing.assert_allclose(out[..., 2][bright] / out[..., 0][bright], 0.6, atol=0.03)


def test_exposure_option_and_time_offset(sample, tmp_path):
    img = tmp_path / "b.png"
    write_image(img, sample.blurry, 16)
    ev = tmp_path / "e.npz"
    shifted = EventStream(sample.events.x, sample.events.y, sample.events.t + 40_000,
                          sample.events.p, W, H)
    write_events_npz(ev, shifted)  # no stored window
    e = sample.exposure
    # window given in the file's unit (µs), then moved onto the events by --time-offset
    r = run(img, ev, "-o", tmp_path / "a", "--exposure", e.start_us, e.end_us,
            "--time-offset", "40ms", "--contrast", "0.2")
    assert r.exit_code == 0, r.output
    meta = json.loads((tmp_path / "a" / "meta.json").read_text())
    assert meta["exposure_us"] == [e.start_us + 40_000, e.end_us + 40_000]
    a = read_image(tmp_path / "a" / "sharp.png")
    assert psnr(a, sample.sharp[3]) > psnr(sample.blurry, sample.sharp[3]) + 4


def test_recording_batch_and_passthrough(sample, tmp_path):
    # two frames on one timeline; the second window lies inside the recording but holds no
    # events (the events resume later): passed through with a warning
    late = EventStream(sample.events.x[-5:], sample.events.y[-5:],
                       sample.events.t[-5:] + 200_000, sample.events.p[-5:], W, H)
    stream = EventStream.concatenate([sample.events, late])
    rec = tmp_path / "rec.h5"
    write_h5(rec, stream, blurry=np.stack([sample.blurry, sample.blurry]),
             exposures=[sample.exposure, Exposure(100_000, 120_000)])
    out = tmp_path / "out"
    r = run(rec, "-o", out, "--contrast", "0.2")
    assert r.exit_code == 0, r.output
    assert "no events" in r.output
    dirs = sorted(p.name for p in out.iterdir() if p.is_dir())
    assert len(dirs) == 2 and (out / "meta.json").exists()
    meta = json.loads((out / "meta.json").read_text())
    assert [f["passthrough"] for f in meta["frames"]] == [False, True]
    second = read_image(out / dirs[1] / "sharp.png")
    np.testing.assert_allclose(second, sample.blurry, atol=1 / 255)


def test_paired_folders(sample, tmp_path):
    (tmp_path / "images").mkdir()
    (tmp_path / "events").mkdir()
    for k in (3, 4):
        write_image(tmp_path / "images" / f"{k:06d}.png", sample.blurry, 16)
        write_events_npz(tmp_path / "events" / f"event{k:06d}.npz", sample.events,
                         [sample.exposure])
    out = tmp_path / "out"
    r = run(tmp_path / "images", tmp_path / "events", "-o", out, "--contrast", "0.2")
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["000003", "000004"]
    assert len(list((out / "000004").glob("frame_*.png"))) == 7


@pytest.mark.parametrize("case", ["size", "outside", "unreadable", "exists", "contrast"])
def test_bad_input_one_line_exit_2_nothing_written(pair, sample, tmp_path, case):
    img, ev = pair
    out = tmp_path / "out"
    args = [img, ev, "-o", out]
    if case == "size":
        write_image(tmp_path / "small.png", sample.blurry[:-2], 16)
        args[0] = tmp_path / "small.png"
    elif case == "outside":
        args += ["--exposure", 10_000_000, 10_020_000]
    elif case == "unreadable":
        (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
        args[0] = tmp_path / "bad.png"
    elif case == "exists":
        out.mkdir()
        (out / "keep.txt").write_text("keep")
    else:
        args += ["--contrast", "-1"]
    r = run(*args)
    assert r.exit_code == 2, r.output
    lines = [line for line in r.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), r.output
    if case == "exists":
        assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]
    else:
        assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if ".tmp" in p.name]


def test_trmd_method_with_tiny_weights(pair, tmp_path):
    from trmd_cli.models import create_model
    from trmd_cli.weights import save_weights

    w = save_weights(tmp_path / "w.safetensors", create_model("test_trmd", n=2), meta={})
    img, ev = pair
    out = tmp_path / "o"
    r = run(img, ev, "-o", out, "--method", "trmd", "--weights", w, "--threads", "1")
    assert r.exit_code == 0, r.output
    meta = json.loads((out / "meta.json").read_text())
    assert meta["method"] == "trmd" and meta["n"] == 2 and meta["weights_hash"]
    from trmd_cli.precision import cpu_has_native_bf16

    assert meta["precision"] == ("bf16" if cpu_has_native_bf16() else "fp32")  # auto
    r = run(img, ev, "-o", tmp_path / "o32", "--method", "trmd", "--weights", w, "--threads",
            "1", "--precision", "fp32")
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "o32" / "meta.json").read_text())["precision"] == "fp32"
    frames = [read_image(out / f"frame_{k:03d}.png") for k in range(5)]
    # TRMD's reconstruction keeps the blurry frame as the mean of its latent frames
    np.testing.assert_allclose(np.mean(frames, axis=0).mean(), read_image(img).mean(),
                               atol=0.01)


# --------------------------------------------------------------------------------------------
# real recordings (skipped without ../shared/data)


@needs_shared
def test_esl_cups_every_frame_sharper(tmp_path):
    base = SHARED / "real" / "esl-cups"
    out = tmp_path / "cups"
    r = run(base / "images", base / "mat", "-o", out, "--compare")
    assert r.exit_code == 0, r.output
    frames = sorted(p for p in out.iterdir() if p.is_dir())
    assert len(frames) == 8
    for folder in frames:
        blurry = read_image(base / "images" / f"{folder.name}.png")
        sharp = read_image(folder / "sharp.png")
        assert sharpness(sharp) > 2.0 * sharpness(blurry), folder.name
        c = json.loads((folder / "meta.json").read_text())["contrast"]
        assert 0.2 < c < 0.7


@needs_shared
def test_ledvdi_bins_path_sharper():
    sio = pytest.importorskip("scipy.io")
    from trmd_cli.edi import EdiBins
    from trmd_cli.threshold import search_contrast

    base = SHARED / "real" / "ledvdi-rotate"
    # (972, 180, 240) int16: 54 frames × 18 bins; frame k uses bins 18(k−2) … 18(k−1) − 1
    bins = sio.loadmat(base / "EventBin3.mat")["event_bins"]
    for k in (20, 40, 50):
        blurry = read_image(base / "blurred" / f"{k:04d}.png")
        model = EdiBins.build(bins[18 * (k - 2): 18 * (k - 1)])
        c = search_contrast(blurry, model).contrast
        sharp = np.clip(model.latent(blurry, [0.5], c)[0], 0, 1)
        assert sharpness(sharp) > 1.3 * sharpness(blurry), k


# --------------------------------------------------------------------------------------------
# exposure windows (trmd_cli.window)


def _memory(stream, frames=(), windows=()):
    from pathlib import Path

    from trmd_cli.read.base import Frame, MemoryRecording

    fl = [Frame(np.zeros((stream.height, stream.width), np.float32), e, i, f"{i}")
          for i, e in enumerate(frames)]
    return MemoryRecording(stream, Path("mem.npz"), "npz", fl, list(windows))


def test_window_rules_in_order(sample):
    from trmd_cli.window import resolve_windows

    ev = sample.events
    first, last = ev.time_range_us
    stored = [Exposure(first, first + 5000)]
    framed = [Exposure(first + 1000, first + 9000), Exposure(first + 9000, last)]
    rec = _memory(ev, frames=framed, windows=stored)
    # 1. the option wins (µs for whole numbers, seconds with a fraction, or --time-unit)
    plan = resolve_windows(rec, (first + 10, first + 20))
    assert plan.source == "option" and plan.windows == [Exposure(first + 10, first + 20)]
    assert resolve_windows(rec, (0.001, 0.002)).windows == [Exposure(1000, 2000)]
    assert resolve_windows(rec, (1, 2), "ms").windows == [Exposure(1000, 2000)]
    # 2. frames stored in the file, 3. stored windows, 4. the events' span (with a warning)
    assert resolve_windows(rec).windows == framed
    assert resolve_windows(_memory(ev, windows=stored)).windows == stored
    plan = resolve_windows(_memory(ev))
    assert plan.source == "span" and plan.windows == [Exposure(first, last)] and plan.warnings
    # the time offset moves every window
    assert resolve_windows(rec, offset_us=-500).windows == [w.shifted(-500) for w in framed]


def test_window_outside_the_events_is_bad_input(sample):
    from trmd_cli.errors import InputError
    from trmd_cli.window import resolve_windows

    ev = sample.events
    first, last = ev.time_range_us
    rec = _memory(ev)
    with pytest.raises(InputError, match="outside the events' time range"):
        resolve_windows(rec, (last + 1000, last + 2000))
    with pytest.raises(InputError, match="empty or reversed"):
        resolve_windows(rec, (first + 20, first + 10))
    # stored frames: all outside → error; some outside → warning (those pass through)
    far = Exposure(last + 10_000, last + 20_000)
    with pytest.raises(InputError):
        resolve_windows(_memory(ev, frames=[far]))
    plan = resolve_windows(_memory(ev, frames=[Exposure(first, last), far]))
    assert len(plan.windows) == 2 and any("outside" in w for w in plan.warnings)
    with pytest.raises(InputError, match="no events"):
        resolve_windows(_memory(EventStream.empty(W, H)))


def test_help_names_the_real_default_method():
    # the help text holds a literal (importing the pipeline for --help would be slow)
    from trmd_cli.cli.deblur import _DEFAULT_METHOD_HELP
    from trmd_cli.pipeline import DEFAULT_METHOD

    assert _DEFAULT_METHOD_HELP == DEFAULT_METHOD
