"""`trmd eval` and trmd_cli.evaluate: figures against hand-computed values, analytic cases for
the no-ground-truth figures (trmd_cli.metrics), JSON structure, and bad input."""

from __future__ import annotations

import json
import math

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.data import SHARED, needs_shared, texture
from trmd_cli.cli.app import app
from trmd_cli.errors import InputError
from trmd_cli.evaluate import evaluate_dataset, parse_methods
from trmd_cli.events import make_stream
from trmd_cli.metrics import (
    consistency,
    consistency_from_counts,
    interval_counts,
    noise_sigma,
    sharpness,
)
from trmd_cli.simulate import MotionRanges, SensorConfig, make_sequence
from trmd_cli.voxel import bins_from_scer, scer_from_bins, scer_voxels
from trmd_cli.write import H5Writer, write_events_npz, write_image, write_text

runner = CliRunner()
N = 3
C_TRUE = 0.1


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def seq():
    """2 consecutive 64×48 exposures of a clean sensor (c = 0.1), 20 px of motion."""
    return make_sequence(texture(120, 160, seed=1), n=N, size=(64, 48), exposure_us=10_000,
                         frames=2, rng=np.random.default_rng(0),
                         sensor=SensorConfig.clean(C_TRUE, eps=0.001),
                         motion=MotionRanges(translation_px=20, rotation_deg=0, scale=0,
                                             perspective=0))


def _write(path, seq, *, sharp=True, contrast=True):
    with H5Writer(path, 64, 48) as w:
        w.add_events(seq.events)
        for k, e in enumerate(seq.exposures):
            w.add_frame(seq.blurry[k], e, sharp=seq.sharp[k] if sharp else None,
                        contrast=seq.contrast if contrast else None)
    return path


@pytest.fixture(scope="module")
def gt_h5(seq, tmp_path_factory):
    return _write(tmp_path_factory.mktemp("gt") / "sim.h5", seq)


@pytest.fixture(scope="module")
def nogt_h5(seq, tmp_path_factory):
    return _write(tmp_path_factory.mktemp("nogt") / "real.h5", seq, sharp=False,
                  contrast=False)


def _psnr_by_hand(a, b):
    return 10 * math.log10(1.0 / np.mean((np.clip(a, 0, 1).astype(np.float64) - b) ** 2))


def _ssim_by_hand(a, b):
    """Wang et al. SSIM with scipy (not the OpenCV path of trmd_cli.metrics)."""
    from scipy.ndimage import correlate

    x = np.arange(11) - 5.0
    g = np.exp(-x * x / (2 * 1.5**2))
    win = np.outer(g, g) / np.outer(g, g).sum()

    def f(img):
        return correlate(img, win, mode="constant")[5:-5, 5:-5]

    a, b = np.clip(a, 0, 1).astype(np.float64), b.astype(np.float64)
    ma, mb = f(a), f(b)
    va, vb, cov = f(a * a) - ma**2, f(b * b) - mb**2, f(a * b) - ma * mb
    c1, c2 = 0.01**2, 0.03**2
    return float(np.mean((2 * ma * mb + c1) * (2 * cov + c2)
                         / ((ma**2 + mb**2 + c1) * (va + vb + c2))))


# ---------------------------------------------------------------------------------------------
# figures against ground truth


def test_blurry_psnr_and_ssim_match_hand_computation(gt_h5, seq):
    rep = evaluate_dataset(gt_h5, ["blurry"], n=N, ground_truth=True)
    assert rep.ground_truth and rep.kind == "trmd-h5" and rep.frames == 2
    scores = rep.method("blurry").frames
    for k, s in enumerate(scores):
        gt = seq.sharp[k]
        per = [_psnr_by_hand(seq.blurry[k], g) for g in gt]
        assert s.psnr_mid == pytest.approx(per[N], abs=1e-6)
        # the sequence figure is the mean of per-frame PSNRs, not the PSNR of the stack
        assert s.psnr_seq == pytest.approx(np.mean(per), abs=1e-6)
        whole = 10 * math.log10(1 / np.mean((seq.blurry[k][None] - gt.astype(np.float64)) ** 2))
        assert abs(s.psnr_seq - whole) > 1e-3
        assert s.ssim_mid == pytest.approx(_ssim_by_hand(seq.blurry[k], gt[N]), abs=1e-6)
        assert s.ssim_seq == pytest.approx(
            np.mean([_ssim_by_hand(seq.blurry[k], g) for g in gt]), abs=1e-6)
    assert rep.method("blurry").mean("psnr_mid") == pytest.approx(
        np.mean([s.psnr_mid for s in scores]))


def test_edi_with_true_contrast_beats_blurry_on_clean_data(gt_h5):
    rep = evaluate_dataset(gt_h5, "blurry,edi-true-c", n=N)
    blurry, edi = rep.method("blurry").frames, rep.method("edi-true-c").frames
    for b, e in zip(blurry, edi, strict=True):
        assert e.contrast == pytest.approx(C_TRUE, rel=1e-6)
        assert e.psnr_seq > b.psnr_seq + 3.0
        assert e.ssim_seq > b.ssim_seq


def test_keep_isolated_reaches_every_edi_of_the_run(gt_h5):
    """`--keep-isolated` gives the true-c twin (built per frame) and the estimating EDI (built
    once) every event; by default they leave the isolated ones out, and score otherwise."""
    both = {}
    for flag in (True, False):
        rep = evaluate_dataset(gt_h5, "edi-true-c,edi", n=N, limit=1, drop_isolated=flag)
        both[flag] = [rep.method(m).frames[0].psnr_seq for m in ("edi-true-c", "edi")]
    assert all(a != b for a, b in zip(both[True], both[False], strict=True)), both
    r = run("eval", gt_h5, "--methods", "edi-true-c", "--limit", "1", "--keep-isolated")
    assert r.exit_code == 0, r.output
    assert f"{both[False][0]:.2f}" in r.output


def test_edi_auto_contrast_beats_blurry(gt_h5):
    rep = evaluate_dataset(gt_h5, "blurry,edi", n=N, limit=1)
    (b,), (e,) = rep.method("blurry").frames, rep.method("edi").frames
    assert 0.03 < e.contrast < 0.3
    assert e.psnr_mid > b.psnr_mid + 2.0


def test_limit_and_progress(gt_h5):
    calls = []
    rep = evaluate_dataset(gt_h5, ["blurry"], n=N, limit=1,
                           progress=lambda d, t: calls.append((d, t)))
    assert rep.frames == 1 and len(rep.method("blurry").frames) == 1
    assert calls == [(1, 1)]


def test_no_true_contrast_skips_edi_true_c_with_a_note(nogt_h5):
    rep = evaluate_dataset(nogt_h5, "blurry,edi-true-c", n=N)
    r = rep.method("edi-true-c")
    assert r.skipped and "true contrast" in r.skipped and r.frames == ()
    assert any("edi-true-c skipped" in note for note in rep.notes)


def test_ground_truth_with_another_n_names_the_right_n(gt_h5):
    with pytest.raises(InputError, match="`n=3`"):
        evaluate_dataset(gt_h5, ["blurry"], n=2)


# ---------------------------------------------------------------------------------------------
# figures without ground truth


def test_noise_sigma_of_white_noise_and_of_smooth_images():
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:200, 0:300] / 300.0
    smooth = 0.2 + 0.3 * x + 0.1 * y + 0.2 * x * y  # bilinear: the kernel removes it exactly
    assert noise_sigma(smooth) == pytest.approx(0.0, abs=1e-12)
    # the kernel is a second difference along y times one along x: an edge along an axis is
    # a function of one coordinate and vanishes; a diagonal edge counts on its two diagonals
    assert noise_sigma(np.where(x > 0.5, 0.8, 0.2)) == 0.0
    diag = np.where(np.arange(300)[None, :] > np.arange(200)[:, None] + 50, 0.8, 0.2)
    assert 0 < noise_sigma(diag) < 0.6 * math.sqrt(math.pi / 2) * 3 / 298
    for sigma in (0.01, 0.05):
        noisy = smooth + rng.normal(0, sigma, smooth.shape)
        assert noise_sigma(noisy) == pytest.approx(sigma, rel=0.03)
    assert noise_sigma(np.stack([smooth + 0.0] * 3, -1)) == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(InputError):
        noise_sigma(np.zeros((2, 9)))


def test_sharpness_of_a_ramp_is_the_squared_slope():
    y, x = np.mgrid[0:20, 0:30].astype(np.float64)
    assert sharpness(0.01 * x + 0.02 * y) == pytest.approx(0.01**2 + 0.02**2, rel=1e-9)
    assert sharpness(np.full((8, 8), 0.3)) == 0.0
    img = 0.01 * x
    assert sharpness(np.stack([img] * 3, -1)) == pytest.approx(sharpness(img))


def _random_events(rng, n, w, h, t0, t1):
    # odd times against instants on a grid of even µs: no event sits exactly on an instant
    t = np.sort(rng.integers(t0 // 2, t1 // 2, n)) * 2 + 1
    return make_stream(rng.integers(0, w, n), rng.integers(0, h, n), t, rng.integers(0, 2, n),
                       w, h)


def test_consistency_is_zero_for_frames_that_follow_the_events(rng):
    w, h, c = 20, 15, 0.15
    ev = _random_events(rng, 600, w, h, 0, 12_000)
    instants = np.linspace(0, 12_000, 2 * N + 1)
    # signed count since instant N, by hand: events with instants[N] < t <= instants[k]
    s = np.zeros((2 * N + 1, h, w))
    for x, y, t, p in zip(ev.x, ev.y, ev.t, ev.p, strict=True):
        for k in range(2 * N + 1):
            if instants[N] < t <= instants[k]:
                s[k, y, x] += p
            elif instants[k] < t <= instants[N]:
                s[k, y, x] -= p
    mid = rng.uniform(0.2, 0.4, (h, w))
    frames = mid[None] * np.exp(c * s)
    assert frames.max() < 1
    assert consistency(frames, ev, instants, c) == pytest.approx(0.0, abs=1e-9)
    # a frozen sequence misses every step: the error is the mean |c·E| over active pixels
    net, active = interval_counts(ev, instants)
    frozen = np.repeat(mid[None], 2 * N + 1, axis=0)
    assert consistency(frozen, ev, instants, c) == pytest.approx(
        c * np.abs(net[active]).mean(), rel=1e-9)
    assert consistency(frames, ev, instants, 2 * c) > 0.05


def test_interval_counts_by_hand():
    ev = make_stream([0, 0, 1, 1, 1], [0, 0, 0, 0, 0], [5, 10, 12, 15, 30], [1, 0, 1, 1, 0],
                     2, 1)
    net, active = interval_counts(ev, [0, 10, 20])
    # (0,10]: pixel 0 gets +1 −1 (active, net 0); (10,20]: pixel 1 gets +2; t=30 is outside
    assert net[:, 0].tolist() == [[0.0, 0.0], [0.0, 2.0]]
    assert active[:, 0].tolist() == [[True, False], [False, True]]


def test_consistency_from_counts_rejects_bad_shapes_and_contrast():
    with pytest.raises(InputError):
        consistency_from_counts(np.ones((3, 4, 4)), np.zeros((3, 4, 4)), 0.2)
    with pytest.raises(InputError):
        consistency_from_counts(np.ones((3, 4, 4)), np.zeros((2, 4, 4)), 0.0)
    assert math.isnan(consistency_from_counts(np.ones((3, 4, 4)), np.zeros((2, 4, 4)), 0.2))


def test_bins_from_scer_inverts_scer(rng):
    bins = rng.integers(-3, 4, (2 * N, 5, 6)).astype(np.float32)
    assert np.array_equal(bins_from_scer(scer_from_bins(bins)), bins)


def test_no_gt_mode_on_simulated_data(gt_h5):
    rep = evaluate_dataset(gt_h5, "blurry,edi-true-c", n=N, ground_truth=False)
    assert not rep.ground_truth
    b, e = rep.method("blurry").frames[0], rep.method("edi-true-c").frames[0]
    assert b.psnr_mid is None and e.ssim_seq is None
    # both judged with the data's true c; EDI's frames follow the events by construction
    assert b.contrast == pytest.approx(C_TRUE, rel=1e-6)
    assert e.consistency < 0.2 * b.consistency
    assert e.sharpness > b.sharpness
    # the sharp frame's edges sit where the events around mid-exposure fired; the blurry
    # one's are smeared along the path (measured 0.77 against 0.90 on this small 64×48 set)
    assert 0.0 <= b.explained < e.explained <= 1.0
    assert e.explained > b.explained + 0.1, (b.explained, e.explained)


def test_no_ground_truth_falls_back_automatically_with_a_note(nogt_h5):
    rep = evaluate_dataset(nogt_h5, ["blurry"], n=N)
    assert not rep.ground_truth
    assert any("no ground truth" in note for note in rep.notes)
    s = rep.method("blurry").frames[0]
    # no true c stored: the reference c is EDI's automatic estimate
    assert s.consistency > 0 and 0.03 < s.contrast < 0.3


def test_parse_methods():
    assert parse_methods("edi, blurry,edi") == ("edi", "blurry")
    with pytest.raises(InputError, match="choose from blurry, edi, edi-true-c, trmd"):
        parse_methods("blurry,deblurgan")
    with pytest.raises(InputError):
        parse_methods(" , ")


# ---------------------------------------------------------------------------------------------
# other dataset layouts


def _to_u8(a):
    return (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)


def test_gopro_style_h5(seq, tmp_path):
    path = tmp_path / "gopro.h5"
    blur = _to_u8(np.repeat(seq.blurry[..., None], 3, -1))
    sharp = _to_u8(np.repeat(seq.sharp[..., None], 3, -1))
    vox = np.stack([scer_voxels(seq.events, e, N) for e in seq.exposures])
    with h5py.File(path, "w") as f:
        f["blur_images"], f["sharp_images"], f["voxel"] = blur, sharp, vox
    rep = evaluate_dataset(path, "blurry,edi,edi-true-c", n=N)
    assert rep.kind == "gopro-h5" and rep.ground_truth and rep.frames == 2
    assert rep.method("edi-true-c").skipped
    s = rep.method("blurry").frames[1]
    b, g = blur[1] / 255.0, sharp[1] / 255.0
    assert s.psnr_mid == pytest.approx(_psnr_by_hand(b, g[N]), abs=1e-6)
    # no raw events: EDI runs on the bins recovered from the voxels, c estimated from them
    for e, bl in zip(rep.method("edi").frames, rep.method("blurry").frames, strict=True):
        assert 0.5 * C_TRUE < e.contrast < 2 * C_TRUE
        assert e.psnr_seq > bl.psnr_seq + 3.0


def test_folder_dataset_with_sharp_frames(seq, tmp_path):
    root = tmp_path / "set"
    (root / "blurry").mkdir(parents=True)
    for k in range(len(seq.exposures)):
        write_image(root / "blurry" / f"{k:04d}.png", seq.blurry[k])
        (root / "sharp" / f"{k:04d}").mkdir(parents=True)
        for j, img in enumerate(seq.sharp[k]):
            write_image(root / "sharp" / f"{k:04d}" / f"{j}.png", img)
    write_text(root / "blurry" / "Exposure_start.txt",
               "".join(f"{e.start_us}\n" for e in seq.exposures))
    write_text(root / "blurry" / "Exposure_end.txt",
               "".join(f"{e.end_us}\n" for e in seq.exposures))
    write_events_npz(root / "events.npz", seq.events)
    rep = evaluate_dataset(root, "blurry,edi", n=N, limit=1)
    assert rep.kind == "folder" and rep.ground_truth and rep.frames == 1
    s = rep.method("blurry").frames[0]
    b, g = _to_u8(seq.blurry[0]) / 255.0, _to_u8(seq.sharp[0]) / 255.0
    assert s.psnr_seq == pytest.approx(np.mean([_psnr_by_hand(b, x) for x in g]), abs=1e-5)
    assert rep.method("edi").frames[0].psnr_mid > s.psnr_mid


# ---------------------------------------------------------------------------------------------
# the command


def test_cli_table_and_json(gt_h5, nogt_h5, tmp_path):
    out = tmp_path / "eval.json"
    r = run("eval", gt_h5, nogt_h5, "--methods", "blurry,edi-true-c,trmd", "--n", N,
            "--json", out)
    assert r.exit_code == 0, r.output
    assert "PSNR mid" in r.output and "consistency" in r.output
    doc = json.loads(out.read_text())
    assert doc["methods"] == ["blurry", "edi-true-c", "trmd"] and doc["n"] == N
    assert doc["protocol"]["psnr"]["data_range"] == 1.0
    d0, d1 = doc["datasets"]
    assert d0["ground_truth"] is True and d1["ground_truth"] is False
    blurry = d0["methods"]["blurry"]
    assert blurry["frames"] == 2 and len(blurry["per_frame"]) == 2
    assert blurry["mean"]["psnr_mid"] == pytest.approx(
        np.mean([f["psnr_mid"] for f in blurry["per_frame"]]), abs=1e-5)
    assert set(blurry["per_frame"][0]) >= {"index", "psnr_mid", "psnr_seq", "ssim_mid",
                                           "ssim_seq", "sharpness", "noise", "consistency",
                                           "seconds"}
    assert d1["methods"]["edi-true-c"]["skipped"]
    # means pooled separately over the sets with and without ground truth
    with_gt, without = doc["overall"]["ground_truth"], doc["overall"]["no_ground_truth"]
    assert with_gt["blurry"]["frames"] == 2 and without["blurry"]["frames"] == 2
    assert with_gt["blurry"]["psnr_seq"] == pytest.approx(blurry["mean"]["psnr_seq"], abs=1e-5)
    assert without["blurry"]["psnr_seq"] is None
    assert without["edi-true-c"]["frames"] == 0


def test_cli_overall_table_for_several_sets(gt_h5):
    r = run("eval", gt_h5, gt_h5, "--methods", "blurry", "--limit", 1)
    assert r.exit_code == 0, r.output
    assert "overall: mean over every frame of 2 datasets with ground truth" in r.output


def test_cli_trmd_with_weights(gt_h5, tmp_path):
    from trmd_cli.models import create_model
    from trmd_cli.models.weights import save_weights

    weights = save_weights(tmp_path / "w.safetensors", create_model("test_trmd", n=N), meta={})
    out = tmp_path / "e.json"
    r = run("eval", gt_h5, "--methods", "trmd", "--weights", weights, "--limit", 1, "--json", out)
    assert r.exit_code == 0, r.output
    s = json.loads(out.read_text())["datasets"][0]["methods"]["trmd"]
    assert s["skipped"] is None and s["frames"] == 1
    assert 5 < s["mean"]["psnr_seq"] < 100


def test_cli_trmd_without_weights_is_skipped_with_a_note(gt_h5, no_shipped_weights):
    r = run("eval", gt_h5, "--methods", "blurry,trmd", "--limit", 1)
    assert r.exit_code == 0, r.output
    assert "trmd skipped" in r.output and "--weights" in r.output


def test_cli_strips(gt_h5, tmp_path):
    from trmd_cli.read import read_image

    strips = tmp_path / "strips"
    r = run("eval", gt_h5, "--methods", "blurry,edi-true-c", "--strip", strips)
    assert r.exit_code == 0, r.output
    files = sorted(strips.iterdir())
    assert [f.name for f in files] == ["sim_000000.png", "sim_000001.png"]
    img = read_image(files[0])
    # blurry | edi-true-c | ground truth, 4 px apart
    assert img.shape[:2] == (48, 3 * 64 + 2 * 4)


def test_cli_outputs_of_the_wrong_kind_are_refused_before_any_work(gt_h5, tmp_path):
    same = tmp_path / "same"
    r = run("eval", gt_h5, "--methods", "blurry", "--strip", same, "--json", same)
    assert r.exit_code == 2 and "--json and --strip name the same path" in r.output
    assert not same.exists()
    kept = tmp_path / "notes.txt"
    kept.write_text("the user's file")
    r = run("eval", gt_h5, "--methods", "blurry", "--strip", kept, "--overwrite")
    assert r.exit_code == 2 and "exists and is not a folder" in r.output
    assert kept.read_text() == "the user's file"
    folder = tmp_path / "folder"
    folder.mkdir()
    r = run("eval", gt_h5, "--methods", "blurry", "--json", folder, "--overwrite")
    assert r.exit_code == 2 and "is a folder, but a file is to be written here" in r.output
    assert folder.is_dir() and not any(folder.iterdir())


def test_cli_windows_that_all_miss_the_events_are_refused(tmp_path, rng):
    """A wrong unit (every window outside the events) is an error, not a table of frames
    passed through unchanged."""
    from tests.helpers.data import random_stream
    from trmd_cli.events import Exposure
    from trmd_cli.write import write_h5

    s = random_stream(rng)
    frames = np.full((2, s.height, s.width), 0.5, np.float32)
    far = [Exposure(10**9, 10**9 + 20_000), Exposure(10**9 + 30_000, 10**9 + 50_000)]
    path = write_h5(tmp_path / "far.h5", s, blurry=frames, exposures=far)
    r = run("eval", path, "--methods", "blurry,edi")
    assert r.exit_code == 2 and "lies outside the events' time range" in r.output, r.output


def test_cli_bad_input(gt_h5, nogt_h5, tmp_path):
    out = tmp_path / "x.json"
    r = run("eval", nogt_h5, "--gt", "--methods", "blurry", "--json", out)
    assert r.exit_code == 2 and "no ground truth" in r.output and "--no-gt" in r.output
    assert not out.exists()
    r = run("eval", gt_h5, "--methods", "blurry,magic")
    assert r.exit_code == 2 and "unknown method 'magic'" in r.output
    r = run("eval", tmp_path / "missing.h5")
    assert r.exit_code == 2 and "not found" in r.output
    out.write_text("{}")
    r = run("eval", gt_h5, "--methods", "blurry", "--json", out)
    assert r.exit_code == 2 and "--overwrite" in r.output
    assert "Traceback" not in r.output


@needs_shared
def test_real_frames_without_ground_truth():
    root = SHARED / "real" / "esl-cups"
    if not root.exists():
        pytest.skip("esl-cups is absent")
    rep = evaluate_dataset(root, "blurry,edi", n=N, limit=1)
    assert rep.kind == "folder" and not rep.ground_truth
    b, e = rep.method("blurry").frames[0], rep.method("edi").frames[0]
    assert e.sharpness > 1.5 * b.sharpness
    assert e.noise > b.noise  # EDI multiplies the sensor's noise into the frame
    assert e.consistency < b.consistency


def test_without_ground_truth_the_report_says_how_to_read_consistency(nogt_h5, tmp_path):
    """EDI's ≈ 0 consistency error is by construction: the table says so, and the JSON too."""
    js = tmp_path / "r.json"
    r = run("eval", nogt_h5, "--methods", "blurry,edi", "--json", js)
    assert r.exit_code == 0, r.output
    text = " ".join(r.stdout.split())
    assert "EDI builds its frames from exactly that relation" in text
    assert "by construction" in json.loads(js.read_text())["protocol"]["consistency"] \
        or "by construction" in json.dumps(json.loads(js.read_text())["protocol"])


# ---------------------------------------------------------------------------------------------
# binned events: a folder of blurry frames with a bins file


def _binned_folder(root, seq, bins_per_frame, *, sharp=True, name="event_bins.npz"):
    from tests.helpers.bins import write_bins
    from trmd_cli.voxel import event_bins

    (root / "blurry").mkdir(parents=True)
    for k in range(len(seq.exposures)):
        write_image(root / "blurry" / f"{k:04d}.png", seq.blurry[k])
        if sharp:
            (root / "sharp" / f"{k:04d}").mkdir(parents=True)
            for j, img in enumerate(seq.sharp[k]):
                write_image(root / "sharp" / f"{k:04d}" / f"{j}.png", img)
    counts = np.stack([event_bins(seq.events, e, bins_per_frame) for e in seq.exposures])
    return root, write_bins(root / name, counts.astype(np.int32))


def test_cli_binned_folder_with_sharp_frames(seq, tmp_path):
    from trmd_cli.methods import EdiMethod
    from trmd_cli.models import create_model
    from trmd_cli.models.weights import save_weights
    from trmd_cli.read import read_image

    root, bins = _binned_folder(tmp_path / "set", seq, 18)
    weights = save_weights(tmp_path / "w.safetensors", create_model("test_trmd", n=N), meta={})
    out = tmp_path / "e.json"
    r = run("eval", root, "--methods", "blurry,edi,trmd", "--weights", weights, "--threads", 1,
            "--json", out)
    assert r.exit_code == 0, r.output
    assert "binned events only (18 bins per frame, no event times)" in r.stderr
    d = json.loads(out.read_text())["datasets"][0]
    assert d["kind"] == "binned" and d["ground_truth"] is True and d["frames"] == 2
    m = d["methods"]
    assert m["trmd"]["skipped"] is None and m["trmd"]["frames"] == 2
    counts = np.load(bins)["event_bins"]
    for k, (e, b) in enumerate(zip(m["edi"]["per_frame"], m["blurry"]["per_frame"],
                                   strict=True)):
        assert e["psnr_mid"] > b["psnr_mid"] + 3
        # the figure is EDI's from_bins on the frame and its bins, scored by hand
        blurry = read_image(root / "blurry" / f"{k:04d}.png")
        truth = read_image(root / "sharp" / f"{k:04d}" / f"{N}.png")
        est = EdiMethod(N).from_bins(blurry, counts[k])
        assert e["contrast"] == pytest.approx(est.contrast, abs=1e-6)  # JSON: 6 decimals
        assert e["psnr_mid"] == pytest.approx(_psnr_by_hand(est.frames[N], truth), abs=1e-5)


def test_cli_binned_folder_without_ground_truth(seq, tmp_path):
    root, _ = _binned_folder(tmp_path / "set", seq, 9, sharp=False, name="EventBin.mat")
    out = tmp_path / "e.json"
    r = run("eval", root, "--methods", "blurry,edi", "--json", out)
    assert r.exit_code == 0, r.output
    assert "9 bins do not split into 2N = 6 equal parts" in " ".join(r.stderr.split())
    d = json.loads(out.read_text())["datasets"][0]
    assert d["kind"] == "binned" and d["ground_truth"] is False
    b, e = d["methods"]["blurry"]["mean"], d["methods"]["edi"]["mean"]
    assert e["sharpness"] > b["sharpness"] and e["consistency"] < b["consistency"]
    assert e["explained"] > b["explained"]
    assert "events explained" in r.stdout


def test_binned_folder_with_two_bins_files_is_bad_input(seq, tmp_path):
    root, bins = _binned_folder(tmp_path / "set", seq, 6, sharp=False)
    np.save(root / "more.npy", np.load(bins)["event_bins"])
    r = run("eval", root, "--methods", "blurry")
    assert r.exit_code == 2
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "holds 2 bins files (event_bins.npz, more.npy)" in lines[0]


@needs_shared
def test_ledvdi_binned_folder_without_ground_truth():
    root = SHARED / "real" / "ledvdi-rotate"
    rep = evaluate_dataset(root, "blurry,edi", n=N, limit=2)
    assert rep.kind == "binned" and not rep.ground_truth and rep.frames == 2
    b, e = rep.method("blurry"), rep.method("edi")
    assert e.mean("sharpness") > b.mean("sharpness")
    assert e.mean("consistency") < b.mean("consistency")
