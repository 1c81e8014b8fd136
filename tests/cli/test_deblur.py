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
    assert 0.1 < meta["contrast"] < 0.4 and "contrast_default" not in meta


def test_a_default_contrast_is_not_called_estimated(pair, tmp_path):
    """A window with too few events falls back to the default c: the run says so, and
    meta.json marks it as the default, not as an estimate."""
    img, ev = pair
    few = tmp_path / "few.npz"
    with np.load(ev) as z:
        keep = {k: z[k] for k in z.files}
    for k in ("x", "y", "t", "p"):
        keep[k] = keep[k][::200]  # a few hundred events: under the estimate's 2000
    np.savez(few, **keep)
    r = run(img, few, "-o", tmp_path / "o", "--method", "edi")
    assert r.exit_code == 0, r.output
    meta = json.loads((tmp_path / "o" / "meta.json").read_text())
    assert meta["contrast"] == 0.25
    assert meta["contrast_default"] is True and meta["contrast_estimated"] is False
    assert "c = 0.250 (the default: too few events to estimate it)" in r.stdout


def test_keep_isolated_is_recorded_and_changes_the_frames(pair, tmp_path):
    """The run's meta says which events EDI left out; `--keep-isolated` keeps them all, and
    the sample's isolated events then change some pixels of the frames."""
    img, ev = pair
    frames = {}
    for flag in ("--drop-isolated", "--keep-isolated"):
        out = tmp_path / flag
        r = run(img, ev, "-o", out, "--contrast", "0.2", flag)
        assert r.exit_code == 0, r.output
        meta = json.loads((out / "meta.json").read_text())
        assert meta["hot_pixels_ignored"] is True
        assert meta["isolated_events_dropped"] is (flag == "--drop-isolated")
        frames[flag] = read_image(out / "frame_000.png")
    assert np.any(frames["--drop-isolated"] != frames["--keep-isolated"])


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
    from trmd_cli.models.weights import save_weights

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


def test_a_window_is_read_in_the_files_unit_and_never_rounded(sample):
    from dataclasses import replace

    from trmd_cli.errors import InputError
    from trmd_cli.window import resolve_windows

    ev = sample.events
    first, _ = ev.time_range_us
    seconds = replace(_memory(ev), times_unit="s")  # a file of float seconds
    assert resolve_windows(seconds, (0, 1)).windows == [Exposure(0, 1_000_000)]
    whole_us = replace(_memory(ev), times_unit="us")  # a file of integer µs
    assert resolve_windows(whole_us, (first, first + 20)).windows == \
        [Exposure(first, first + 20)]
    # a fraction still says seconds, as in files; µs set by the user must be whole
    assert resolve_windows(whole_us, (0.001, 0.002)).windows == [Exposure(1000, 2000)]
    with pytest.raises(InputError, match=r"\.5 µs, not a whole number of microseconds"):
        resolve_windows(whole_us, (first, first + 20.5), "us")
    with pytest.raises(InputError, match="out of range"):
        resolve_windows(whole_us, (0, 1e25))
    # --time-unit wins over the file's
    assert resolve_windows(seconds, (1, 2), "ms").windows == [Exposure(1000, 2000)]


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
    # the help text holds a literal (importing the methods for --help would be slow)
    from trmd_cli.cli.deblur import _DEFAULT_METHOD_HELP
    from trmd_cli.methods import DEFAULT_METHOD

    assert _DEFAULT_METHOD_HELP == DEFAULT_METHOD


def test_sparse_frames_get_one_summary_line_about_c(sample, tmp_path):
    """Five frames, each with too few events to estimate c: one line naming how many frames
    and why, not five; nothing about clipping when (almost) nothing was clipped."""
    rng = np.random.default_rng(0)
    k, per = 5, 300
    t = np.concatenate([np.sort(rng.integers(30_000 * i, 30_000 * i + 20_000, per))
                        for i in range(k)])
    stream = EventStream(rng.integers(0, W, k * per).astype(np.uint16),
                         rng.integers(0, H, k * per).astype(np.uint16), t.astype(np.int64),
                         rng.choice(np.array([-1, 1], np.int8), k * per), W, H)
    rec = tmp_path / "rec.h5"
    write_h5(rec, stream, blurry=np.full((k, H, W), 0.4, np.float32),
             exposures=[Exposure(30_000 * i, 30_000 * i + 20_000) for i in range(k)])
    r = run(rec, "-o", tmp_path / "out")
    assert r.exit_code == 0, r.output
    lines = [ln for ln in r.stderr.splitlines() if "default c" in ln]
    assert len(lines) == 1, r.stderr
    # nearly all of a frame's 300 random events are isolated: left out, and said so
    assert "5 of 5 frames" in lines[0] and "too few events (" in lines[0]
    assert "of the window's 300 events" in lines[0] and "--keep-isolated" in lines[0]
    assert "--contrast" in lines[0]
    assert "clipped" not in r.stderr


def test_contrast_notes_count_frames_by_kind():
    from trmd_cli.deblur import ContrastNotes, FrameResult
    from trmd_cli.methods import Estimate

    def result(name, note, reliable=True):
        est = Estimate(np.zeros((1, 2, 2), np.float32), np.zeros(1), 0.05, True, reliable,
                       contrast_note=note)
        return FrameResult(0, name, np.zeros((2, 2), np.float32), Exposure(0, 10), est, 5)

    notes = ContrastNotes()
    for r in (result("a", None), result("b", "edge"), result("c", "edge"),
              result("d", "few", reliable=False)):
        notes.add(r)
    assert notes.lines() == ["frame d: few — set `contrast` if you know it",
                             "2 of 4 frames (the first, b): edge — set `contrast` if you know it"]


@pytest.mark.parametrize("fmt", ["mat", "txt"])
def test_image_and_sizeless_events_take_the_sensor_size_from_the_image(sample, tmp_path, fmt):
    """Events that never reach the last columns: the sensor is the image's size, not the
    largest coordinate + 1."""
    keep = sample.events.x < W - 10
    s = sample.events
    img = tmp_path / "blurry.png"
    write_image(img, sample.blurry, 16)
    ev = tmp_path / f"events.{fmt}"
    if fmt == "mat":
        sio = pytest.importorskip("scipy.io")
        sio.savemat(ev, {"t": s.t[keep] / 1e6, "x": s.x[keep].astype(float),
                         "y": s.y[keep].astype(float), "p": (s.p[keep] > 0).astype(float),
                         "start_timestamp": np.array([[sample.exposure.start_us / 1e6]]),
                         "end_timestamp": np.array([[sample.exposure.end_us / 1e6]])})
    else:
        rows = [f"{t / 1e6:.6f} {x} {y} {int(p > 0)}"
                for t, x, y, p in zip(s.t[keep], s.x[keep], s.y[keep], s.p[keep])]
        ev.write_text("\n".join(rows) + "\n")
    args = [img, ev, "-o", tmp_path / "out", "--contrast", "0.2"]
    if fmt == "txt":
        args += ["--exposure", f"{sample.exposure.start_us / 1e6}",
                 f"{sample.exposure.end_us / 1e6}"]
    r = run(*args)
    assert r.exit_code == 0, r.output
    assert "stores no sensor size" not in r.stderr
    assert read_image(tmp_path / "out" / "sharp.png").shape == (H, W)


def test_events_only_file_alone_says_the_image_is_missing(tmp_path, sample):
    ev = tmp_path / "events.npz"
    write_events_npz(ev, sample.events)
    for extra in ([], ["--exposure", "0", "1000"]):
        r = run(ev, "-o", tmp_path / "out", *extra)
        assert r.exit_code == 2
        assert "events only" in r.stderr or "no frames" in r.stderr, r.stderr
        assert "blurry image before it" in r.stderr
        assert "frames carry their own" not in r.stderr
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------
# binned events (IMAGES_DIR BINS_FILE): no event times


B = 18  # bins per frame: 2N = 6 divides it, every latent instant is a bin edge


@pytest.fixture(scope="module")
def binned(sample):
    from tests.helpers.bins import binned_frames

    return binned_frames(sample, B)


def _frames_u8(folder) -> list[np.ndarray]:
    import cv2

    return [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in sorted(folder.glob("frame_*.png"))]


def _fractions(path) -> list[float]:
    lines = path.read_text().splitlines()
    assert lines[0].startswith("# file fraction")
    return [float(ln.split()[1]) for ln in lines[1:]]


def test_binned_mat_deblurs_with_edi_like_from_bins(binned, tmp_path):
    from tests.helpers.bins import write_binned_set
    from trmd_cli.methods import EdiMethod
    from trmd_cli.write import to_uint

    images, bins = write_binned_set(tmp_path / "set", binned, "mat", "flat")
    out = tmp_path / "out"
    r = run(images, bins, "-o", out, "--contrast", "0.2", "--compare")
    assert r.exit_code == 0, r.output
    said = [ln for ln in r.stderr.splitlines() if "binned events" in ln]
    assert len(said) == 1 and "18 bins per frame" in said[0] and "hot pixels" in said[0]
    assert "wrote" in r.stdout and "2 frames × 7 latent frames (edi, N=3)" in r.stdout
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["0002", "0003"]
    for name, f in zip(("0002", "0003"), binned, strict=True):
        folder = out / name
        # far sharper than the blurry frame against the simulator's middle frame
        sharp = read_image(folder / "sharp.png")
        assert psnr(sharp, f.sharp[3]) > psnr(f.blurry, f.sharp[3]) + 8, name
        # bit-identical to the method called directly on the frame as read and its bins
        blurry = read_image(images / f"{name}.png")
        est = EdiMethod(3, 0.2).from_bins(blurry, f.bins)
        for got, want in zip(_frames_u8(folder), est.frames, strict=True):
            np.testing.assert_array_equal(got, to_uint(want, 8))
        # instants as fractions k/2N of the exposure, written as the very floats the method
        # used (read back equal, not rounded); no µs anywhere
        assert _fractions(folder / "timestamps.txt") == est.instants_us.tolist()
        np.testing.assert_allclose(est.instants_us, np.arange(7) / 6, rtol=0, atol=1e-15)
        meta = json.loads((folder / "meta.json").read_text())
        assert meta["binned"] is True and meta["bins_per_frame"] == B
        assert meta["fractions"] == est.instants_us.tolist()
        assert not {"exposure_us", "instants_us", "time_offset_us"} & set(meta)
        assert meta["abs_count"] == int(np.abs(f.bins.astype(int)).sum())
        assert (folder / "compare.png").exists()
    top = json.loads((out / "meta.json").read_text())
    assert top["binned"] is True and len(top["frames"]) == 2 and "time_offset_us" not in top


@pytest.mark.parametrize("fmt", ["npy", "npz"])
def test_binned_flat_and_4d_arrays_give_the_same_output(binned, tmp_path, fmt):
    from tests.helpers.bins import write_binned_set

    outs = []
    for layout in ("flat", "4d"):
        images, bins = write_binned_set(tmp_path / layout, binned, fmt, layout)
        out = tmp_path / f"out-{layout}"
        r = run(images, bins, "-o", out, "--n", "2", "--bit-depth", "16")
        assert r.exit_code == 0, r.output
        outs.append(out)
    for name in ("0002", "0003"):
        a, b = (_frames_u8(o / name) for o in outs)
        assert len(a) == 5 and a[0].dtype == np.uint16
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)
        assert (json.loads((outs[0] / name / "meta.json").read_text())["contrast"]
                == json.loads((outs[1] / name / "meta.json").read_text())["contrast"])


def test_binned_odd_bin_count_says_how_it_places_the_instants(sample, tmp_path):
    from tests.helpers.bins import binned_frames, write_binned_set

    frames = binned_frames(sample, 9)  # 2N = 6 does not divide 9
    images, bins = write_binned_set(tmp_path / "set", frames, "npy", "4d")
    r = run(images, bins, "-o", tmp_path / "out", "--contrast", "0.2")
    assert r.exit_code == 0, r.output
    said = [ln for ln in r.stderr.splitlines() if "binned events" in ln]
    assert len(said) == 1 and "9 bins do not split into 6 equal parts" in said[0]
    sharp = read_image(tmp_path / "out" / "0002" / "sharp.png")
    assert psnr(sharp, frames[0].sharp[3]) > psnr(frames[0].blurry, frames[0].sharp[3]) + 8


@pytest.mark.parametrize("bins_per_frame", [12, 18])
def test_binned_trmd_with_tiny_weights(sample, tmp_path, bins_per_frame):
    """N = 2: 12 bins are summed three by three, 18 are split where a bin straddles an
    instant; either way the network runs on the counts as TrmdMethod.from_bins does."""
    from tests.helpers.bins import binned_frames, write_binned_set
    from trmd_cli.methods import TrmdMethod
    from trmd_cli.models import create_model
    from trmd_cli.models.weights import save_weights
    from trmd_cli.write import to_uint

    w = save_weights(tmp_path / "w.safetensors", create_model("test_trmd", n=2), meta={})
    frames = binned_frames(sample, bins_per_frame)
    images, bins = write_binned_set(tmp_path / "set", frames, "mat", "flat")
    out = tmp_path / "o"
    r = run(images, bins, "-o", out, "--method", "trmd", "--weights", w, "--threads", "1",
            "--precision", "fp32")
    assert r.exit_code == 0, r.output
    method = TrmdMethod(2, w, threads=1, precision="fp32")
    said = [ln for ln in r.stderr.splitlines() if "binned events" in ln]
    assert len(said) == 1
    assert ("timing inputs get the counts" in said[0]) == method.needs.timing
    assert ("do not split" in said[0]) == (bins_per_frame % 4 != 0)
    meta = json.loads((out / "0002" / "meta.json").read_text())
    assert meta["method"] == "trmd" and meta["n"] == 2 and meta["binned"]
    assert _fractions(out / "0002" / "timestamps.txt") == [0, 0.25, 0.5, 0.75, 1]
    est = method.from_bins(read_image(images / "0003.png"), frames[1].bins)
    for got, want in zip(_frames_u8(out / "0003"), est.frames, strict=True):
        np.testing.assert_array_equal(got, to_uint(want, 8))


def test_binned_trmd_with_the_shipped_weights(binned, tmp_path):
    from tests.helpers.bins import write_binned_set
    from trmd_cli.methods import MethodConfig, unavailable

    if unavailable(MethodConfig("trmd")):
        pytest.skip("this installation ships no weights")
    images, bins = write_binned_set(tmp_path / "set", binned, "npy", "4d")
    out = tmp_path / "o"
    r = run(images, bins, "-o", out, "--method", "trmd", "--threads", "1")
    assert r.exit_code == 0, r.output
    said = [ln for ln in r.stderr.splitlines() if "binned events" in ln]
    assert len(said) == 1 and "timing inputs get the counts" in said[0]
    for name, f in zip(("0002", "0003"), binned, strict=True):
        sharp = read_image(out / name / "sharp.png")
        assert psnr(sharp, f.sharp[3]) > psnr(f.blurry, f.sharp[3]) + 5, name


@pytest.mark.parametrize("case", ["rows", "frames", "fraction", "nan", "size", "dtype",
                                  "offset", "exposure", "time-unit", "motion"])
def test_binned_bad_input_one_line_exit_2_nothing_written(binned, tmp_path, case):
    from tests.helpers.bins import write_binned_set, write_bins

    images, bins = write_binned_set(tmp_path / "set", binned, "npy", "flat")
    counts = np.load(bins)
    args = []
    expect = ""
    if case == "rows":  # 37 rows for 2 frames
        write_bins(bins, np.concatenate([counts, counts[:1]]))
        expect = "37 bins, which 2 frames do not divide"
    elif case == "frames":  # (3, B, H, W) for 2 images
        write_bins(bins, np.stack([counts[:B], counts[B:], counts[:B]]))
        expect = "bins of 3 frames, the images number 2"
    elif case == "fraction":
        f = counts.astype(np.float64)
        f[20, 5, 7] = 0.5
        write_bins(bins, f)
        expect = "frame 1, bin 2 holds a count that is not a whole number (0.5)"
    elif case == "nan":
        f = counts.astype(np.float32)
        f[3, 1, 1] = np.nan
        write_bins(bins, f)
        expect = "frame 0, bin 3 holds NaN"
    elif case == "size":
        write_bins(bins, counts[:, :-1])
        expect = f"the bins are {W}x{H - 1} but the frames are {W}x{H}"
    elif case == "dtype":
        write_bins(bins, counts > 0)
        expect = "expected integer counts"
    elif case == "offset":
        args = ["--time-offset", "-40ms"]
        expect = "no event clock: --time-offset"
    elif case == "exposure":
        args = ["--exposure", "0", "1"]
        expect = "no event clock: --exposure"
    elif case == "motion":  # no event times to find a motion in; fused runs without them
        args = ["--method", "motion"]
        expect = "the motion method needs event times to estimate the motion; binned events " \
            "have none — use the fused method"
    else:
        args = ["--time-unit", "ms"]
        expect = "--time-unit does not apply"
    out = tmp_path / "out"
    r = run(images, bins, "-o", out, *args)
    assert r.exit_code == 2, r.output
    lines = [line for line in r.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), r.output
    assert expect in lines[0], lines[0]
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if ".tmp" in p.name]


def test_binned_file_given_as_events_points_to_the_frames_folder(binned, tmp_path):
    from tests.helpers.bins import write_binned_set

    images, bins = write_binned_set(tmp_path / "set", binned, "mat", "flat")
    r = run(images / "0002.png", bins, "-o", tmp_path / "out")
    assert r.exit_code == 2
    assert "holds binned events" in r.stderr and "IMAGES_DIR BINS_FILE" in r.stderr
    assert not (tmp_path / "out").exists()


def test_binned_frames_without_events_pass_through(binned, tmp_path):
    from tests.helpers.bins import BinnedFrame, write_binned_set

    silent = BinnedFrame(binned[1].blurry, np.zeros_like(binned[1].bins), binned[1].sharp)
    images, bins = write_binned_set(tmp_path / "set", [binned[0], silent], "npy", "4d")
    r = run(images, bins, "-o", tmp_path / "out", "--contrast", "0.2")
    assert r.exit_code == 0, r.output
    assert "frame 0003: its bins hold no events; passed through" in r.stderr
    assert "(1 passed through without events)" in r.stdout
    np.testing.assert_allclose(read_image(tmp_path / "out" / "0003" / "sharp.png"),
                               read_image(images / "0003.png"), atol=1 / 255)


# real binned events: LEDVDI (skipped without ../shared/data)


@needs_shared
def test_ledvdi_deblur_every_frame_sharper(tmp_path):
    """The real command on all 54 frames (c given: the estimate costs ~0.5 s a frame).

    Sharpness after a 3×3 median on both frames: the Laplacian counts speckle as detail, and
    EDI's speckle is what leaving out the isolated events removes (measured: 1.70× → 1.53×
    the blurry frames' Laplacian variance on average, 1.27× → 1.26× after the median). Some
    frames are barely blurred: each must gain, the recording by a fifth."""
    import cv2

    base = SHARED / "real" / "ledvdi-rotate"
    out = tmp_path / "ledvdi"
    r = run(base / "blurred", base / "EventBin3.mat", "-o", out, "--contrast", "0.4")
    assert r.exit_code == 0, r.output
    assert "18 bins per frame" in r.stderr
    folders = sorted(p for p in out.iterdir() if p.is_dir())
    assert [p.name for p in folders] == [f"{k:04d}" for k in range(2, 56)]
    gains = []
    for folder in folders:
        blurry = read_image(base / "blurred" / f"{folder.name}.png")
        sharp = np.clip(read_image(folder / "sharp.png"), 0, 1)
        gains.append(sharpness(cv2.medianBlur(sharp, 3)) / sharpness(cv2.medianBlur(blurry, 3)))
        assert gains[-1] > 1.0, folder.name
    assert np.mean(gains) > 1.2, gains


@needs_shared
def test_ledvdi_auto_contrast_on_a_few_frames(tmp_path):
    """`--method edi` as the user runs it (c estimated per frame) on three frames: their images
    and their rows of EventBin3.mat, paired by sorted order as in the whole set."""
    import shutil

    sio = pytest.importorskip("scipy.io")
    from tests.helpers.bins import write_bins

    base = SHARED / "real" / "ledvdi-rotate"
    counts = sio.loadmat(base / "EventBin3.mat")["event_bins"]
    (tmp_path / "blurred").mkdir()
    picked = (20, 40, 50)
    for k in picked:
        shutil.copy(base / "blurred" / f"{k:04d}.png", tmp_path / "blurred")
    bins = write_bins(tmp_path / "bins.npy",
                      np.concatenate([counts[18 * (k - 2): 18 * (k - 1)] for k in picked]))
    out = tmp_path / "out"
    r = run(tmp_path / "blurred", bins, "-o", out)
    assert r.exit_code == 0, r.output
    for k in picked:
        blurry = read_image(base / "blurred" / f"{k:04d}.png")
        sharp = read_image(out / f"{k:04d}" / "sharp.png")
        assert sharpness(sharp) > 1.3 * sharpness(blurry), k
