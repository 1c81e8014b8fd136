"""Fine-tuning without ground truth: the motion grids and the two motion losses against hand
computations, the settings' refusals, and `trmd finetune` end to end on a small simulated set
(weights that deblur, eval and info take, a held-out picture, one-line errors)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from tests.helpers.cli import assert_one_error_line
from tests.helpers.data import texture
from trmd_cli.cli.app import app
from trmd_cli.errors import InputError
from trmd_cli.motion.model import GlobalMotion
from trmd_cli.simulate import MotionRanges, SensorConfig, make_sequence
from trmd_cli.train.finetune import (
    FinetuneConfig,
    Window,
    crop_batch,
    motion_grid,
    split_windows,
    window_batch,
)
from trmd_cli.train.losses import deconv_loss, reblur_loss, warp_loss
from trmd_cli.write import H5Writer

runner = CliRunner()


def _pixel(grid: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """grid_sample's corner-aligned coordinates back to pixels."""
    return (grid[..., 0] + 1) * (w - 1) / 2, (grid[..., 1] + 1) * (h - 1) / 2


def test_motion_grid_of_a_translation_is_the_shift_by_hand():
    # 8 px to the right over the exposure: at u the image is 8·(u − ½) px right of the middle
    # frame, so crop pixel (x, y) shows the middle frame's (x − 8·(u − ½), y)
    motion = GlobalMotion(velocity=(8.0, 0.0), centre=(20.0, 15.0))
    box = (5, 3, 20, 10)
    grid, inside = motion_grid(motion, np.array([0.0, 0.5, 1.0]), box)
    assert grid.shape == (3, 10, 20, 2) and inside.shape == (3, 10, 20)
    px, py = _pixel(grid, 20, 10)
    cols = np.arange(20, dtype=np.float64)
    np.testing.assert_allclose(px[0, 4], cols + 4, atol=1e-5)   # u = 0: 4 px to the left
    np.testing.assert_allclose(px[1, 4], cols, atol=1e-5)
    np.testing.assert_allclose(px[2, 4], cols - 4, atol=1e-5)
    np.testing.assert_allclose(py[:, :, 7], np.broadcast_to(np.arange(10.0)[None], (3, 10)),
                               atol=1e-5)
    # inside: the 4 columns carried past the crop's edge are not
    assert inside[0, :, :16].all() and not inside[0, :, 16:].any()
    assert inside[1].all()
    assert not inside[2, :, :4].any() and inside[2, :, 4:].all()


def _translation_case(shift_px: float = 6.0, j: int = 25):
    """A sharp middle frame, its blur by a known horizontal translation computed with the
    same sampling the loss uses, and the batch the reblur loss reads."""
    h, w = 24, 40
    sharp = texture(h, w, seed=3).astype(np.float32)
    motion = GlobalMotion(velocity=(shift_px, 0.0), centre=(w / 2, h / 2))
    fr = (np.arange(j) + 0.5) / j
    grid, inside = motion_grid(motion, fr, (0, 0, w, h))
    # the blur by hand: the mean of the shifted copies, linear interpolation along x
    xs = np.arange(w)[None, None, :] - shift_px * (fr[:, None, None] - 0.5)
    x0 = np.clip(np.floor(xs).astype(int), 0, w - 1)
    x1 = np.clip(x0 + 1, 0, w - 1)
    a = xs - np.floor(xs)
    rows = np.arange(h)[None, :, None]
    blurry = ((1 - a) * sharp[rows, x0] + a * sharp[rows, x1]).mean(0).astype(np.float32)
    batch = {"blurry": torch.from_numpy(blurry)[None, None],
             "reblur_grid": torch.from_numpy(grid)[None],
             "reblur_mask": torch.from_numpy(inside.all(0)[None, None].astype(np.float32))}
    return sharp, blurry, batch


def _outputs(mid: np.ndarray, n: int = 1) -> dict:
    latent = torch.from_numpy(np.stack([mid] * (2 * n + 1)))[None, :, None]
    return {"latent": latent}


def test_reblur_loss_is_zero_for_the_sharp_frame_and_not_for_the_blurry_one():
    sharp, blurry, batch = _translation_case()
    recipe = FinetuneConfig(penalty="mse").recipe()
    assert float(reblur_loss(_outputs(sharp), batch, recipe)) < 1e-10
    wrong = float(reblur_loss(_outputs(blurry), batch, recipe))
    # the blurry frame as the answer is blurred twice: an error of the order of its detail
    assert wrong > 1e-4
    # and the loss only looks where the mask says
    masked = dict(batch, reblur_mask=torch.zeros_like(batch["reblur_mask"]))
    assert float(reblur_loss(_outputs(blurry), masked, recipe)) == 0.0


def test_warp_loss_is_zero_for_frames_that_follow_the_motion():
    h, w, n = 20, 36, 1
    mid = texture(h, w, seed=5).astype(np.float32)
    motion = GlobalMotion(velocity=(4.0, 0.0), centre=(w / 2, h / 2))
    grid, inside = motion_grid(motion, np.arange(2 * n + 1) / (2 * n), (0, 0, w, h))
    # k = 0 at u = 0: shown 2 px left of the middle frame, i.e. pixel x shows mid[x + 2]
    frames = np.stack([np.roll(mid, -2, axis=1), mid, np.roll(mid, 2, axis=1)])
    latent = torch.from_numpy(frames)[None, :, None]
    mask = inside.copy()
    mask[:, :, :3] = False
    mask[:, :, -3:] = False  # np.roll wraps around: not the motion there
    batch = {"warp_grid": torch.from_numpy(grid)[None],
             "warp_mask": torch.from_numpy(mask[:, None][None].astype(np.float32))}
    recipe = FinetuneConfig(penalty="mse").recipe()
    assert float(warp_loss({"latent": latent}, batch, recipe)) < 1e-10
    still = torch.from_numpy(np.stack([mid] * 3))[None, :, None]
    assert float(warp_loss({"latent": still}, batch, recipe)) > 1e-4


def test_deconv_loss_counts_only_where_the_guard_trusts_the_deconvolution():
    rng = np.random.default_rng(0)
    target = torch.from_numpy(rng.random((1, 3, 1, 6, 8), dtype=np.float32))
    mask = torch.zeros(1, 3, 1, 6, 8)
    mask[:, :, :, :, :4] = 1.0  # trusted on the left half only
    latent = target.clone()
    latent[..., 4:] += 0.5       # wrong where it is not trusted: no cost
    recipe = FinetuneConfig(penalty="mse").recipe()
    batch = {"deconv": target, "deconv_mask": mask}
    assert float(deconv_loss({"latent": latent}, batch, recipe)) == 0.0
    latent[..., :4] += 0.1       # wrong where it is: the mean squared error over those pixels
    assert float(deconv_loss({"latent": latent}, batch, recipe)) == pytest.approx(0.01, rel=1e-5)
    with pytest.raises(InputError, match="deconvolution"):
        deconv_loss({"latent": latent}, {}, recipe)


def test_motion_losses_refuse_data_without_a_motion():
    recipe = FinetuneConfig().recipe()
    outputs = {"latent": torch.zeros(1, 3, 1, 8, 8)}
    for loss in (reblur_loss, warp_loss):
        with pytest.raises(InputError, match="needs the exposure's motion"):
            loss(outputs, {"blurry": torch.zeros(1, 1, 8, 8)}, recipe)


@pytest.mark.parametrize("kw, needle", [
    ({"losses": {"middle": 1.0}}, "needs sharp frames"),
    ({"losses": {"nonsense": 1.0}}, "unknown loss"),
    ({"losses": {"reblur": 0.0}}, "no fine-tuning loss"),
    ({"holdout": 1.0}, "holdout"),
    ({"crop": 8}, "crop"),
])
def test_config_refuses_what_cannot_train(kw, needle):
    with pytest.raises(InputError, match=needle):
        FinetuneConfig(**kw)


def _window(i: int, h: int = 30, w: int = 50, trusted: bool = True) -> Window:
    rng = np.random.default_rng(i)
    return Window(f"w{i}", rng.random((h, w), dtype=np.float32),
                  rng.integers(-2, 3, (6, h, w)).astype(np.float32), None, 0.2,
                  GlobalMotion(velocity=(3.0, 1.0), centre=(w / 2, h / 2)), trusted)


def test_split_holds_out_every_kth_window_and_keeps_the_rest():
    windows = [_window(i, 4, 4) for i in range(10)]
    train, held = split_windows(windows, 0.2)
    assert [w.name for w in held] == ["w2", "w7"]
    assert len(train) == 8 and not {w.name for w in train} & {"w2", "w7"}
    assert split_windows(windows[:1], 0.5) == (windows[:1], [])


def test_batches_have_the_shapes_the_losses_read_and_untrusted_motion_is_masked():
    windows = [_window(0), _window(1, trusted=False)]
    b = crop_batch(windows, np.random.default_rng(0), 5, 16, 48)
    assert b["blurry"].shape == (5, 1, 16, 16) and b["voxels"].shape == (5, 6, 16, 16)
    j = b["reblur_grid"].shape[1]
    assert 3 <= j <= 48 and b["reblur_grid"].shape == (5, j, 16, 16, 2)
    assert b["warp_grid"].shape == (5, 7, 16, 16, 2)
    assert b["warp_mask"].shape == (5, 7, 1, 16, 16)
    whole = window_batch(windows[1], 48)
    assert whole["blurry"].shape == (1, 1, 30, 50)
    assert float(whole["reblur_mask"].sum()) == 0 and float(whole["warp_mask"].sum()) == 0
    assert float(window_batch(windows[0], 48)["reblur_mask"].sum()) > 0


def test_where_the_guard_fell_back_no_motion_term_teaches():
    from dataclasses import replace

    weight = np.ones((7, 30, 50), np.float32)
    weight[:, :, 25:] = 0.0  # an object moving on its own in the right half
    weight[6, :10, :] = 0.0  # and the last instant's top rows
    win = replace(_window(0), deconv=np.zeros((7, 30, 50), np.float32), deconv_weight=weight)
    plain = window_batch(_window(0), 48)
    b = window_batch(win, 48)
    assert float(plain["reblur_mask"][..., 25:].sum()) > 0
    assert float(b["reblur_mask"][..., 25:].sum()) == 0
    assert float(b["warp_mask"][..., 25:].sum()) == 0
    assert float(b["warp_mask"][0, 6, :, :10].sum()) == 0
    assert float(b["warp_mask"][0, 5, :, :10].sum()) > 0
    torch.testing.assert_close(b["reblur_mask"][..., :25], plain["reblur_mask"][..., :25])


def test_the_oracle_learns_from_the_sharp_frames_and_is_off_without_them():
    from dataclasses import replace

    from trmd_cli.models.weights import load_weights
    from trmd_cli.train.finetune import held_out_losses, tune

    with pytest.raises(InputError, match="needs sharp frames"):
        FinetuneConfig(losses={"sequence": 1.0})
    cfg = FinetuneConfig(losses={"sequence": 1.0}, oracle=True, steps=15, crop=32,
                         batch_size=2, lr=1e-3, anchor=0.0)
    rng = np.random.default_rng(5)
    # a flat frame with one bright square: the true frames are known, the network's are not
    sharp = np.full((7, 32, 48), 0.3, np.float32)
    sharp[:, 8:20, 12:30] = 0.8
    win = replace(_window(3, 32, 48), blurry=sharp[3].copy(), sharp=sharp,
                  voxels=rng.integers(-1, 2, (6, 32, 48)).astype(np.float32))
    assert window_batch(win, 48)["sharp"].shape == (1, 7, 1, 32, 48)
    model, _ = load_weights(None, device="cpu")
    before = held_out_losses(model, [win], cfg)["sequence"]
    tune(model, [win], cfg)
    after = held_out_losses(model, [win], cfg)["sequence"]
    assert after < 0.7 * before, (before, after)
    with pytest.raises(InputError, match="sharp frames"):
        held_out_losses(model, [_window(4, 32, 48)], cfg)


# --- the command ------------------------------------------------------------------------------

W, H = 96, 72


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """4 exposures of a camera shake, a sensor with c = 0.3 (no ground truth is read)."""
    seq = make_sequence(texture(200, 260, seed=4), n=3, size=(W, H), exposure_us=20_000,
                        frames=4, rng=np.random.default_rng(2),
                        sensor=SensorConfig.clean(0.3, eps=0.001),
                        motion=MotionRanges(translation_px=12, rotation_deg=1, scale=0.0,
                                            perspective=0.0))
    d = tmp_path_factory.mktemp("finetune")
    path = d / "cam.h5"
    with H5Writer(path, W, H) as w:
        w.add_events(seq.events)
        for k, e in enumerate(seq.exposures):
            w.add_frame(seq.blurry[k], e)
    return path


@pytest.fixture(scope="module")
def tuned(sim, tmp_path_factory):
    out = tmp_path_factory.mktemp("tuned") / "cam.safetensors"
    r = runner.invoke(app, ["finetune", str(sim), "-o", str(out), "--steps", "2", "--crop",
                            "32", "--batch-size", "2", "--holdout", "0.25", "--threads", "1"])
    assert r.exit_code == 0, r.output
    return out, r


def test_finetune_writes_weights_that_the_other_commands_take(tuned, sim, tmp_path):
    out, r = tuned
    assert "held-out losses (1 window(s))" in r.stdout
    pic = out.with_suffix(".png")
    import imageio.v3 as iio

    strip = iio.imread(pic)
    assert strip.shape[0] >= H and strip.shape[1] >= 3 * W  # blurry | before | after

    info = runner.invoke(app, ["info", str(out), "--json"])
    assert info.exit_code == 0, info.output
    meta = json.loads(info.stdout)
    record = meta["finetune"]
    assert record is not None, meta
    assert record["inputs"] == ["cam.h5"] and record["windows"] == 3 and record["held_out"] == 1
    assert record["steps"] == 2
    from trmd_cli.models.weights import load_weights

    tuned_net, _ = load_weights(out)
    start, _ = load_weights(None)
    assert any(not torch.equal(p, q) for p, q in zip(tuned_net.parameters(),
                                                     start.parameters(), strict=True))

    d = runner.invoke(app, ["deblur", str(sim), "-o", str(tmp_path / "d"), "--weights",
                            str(out), "--threads", "1"])
    assert d.exit_code == 0, d.output
    assert len(list((tmp_path / "d").glob("*/frame_*.png"))) == 4 * 7


def test_a_log_gets_training_progress_lines(tuned):
    _, r = tuned  # stderr is not a terminal under the runner, as in `… > log 2>&1`
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("fine-tuning step")]
    assert [ln.split(":")[0] for ln in lines] == ["fine-tuning step 1/2", "fine-tuning step 2/2"]


@pytest.mark.parametrize("total, expected", [(2, [1, 2]), (30, [1, 3, 6, 9, 12, 15, 18, 21,
                                                                  24, 27, 30])])
def test_plain_progress_marks_the_first_every_tenth_and_the_last_step(total, expected):
    from trmd_cli.cli.finetune import plain_line

    assert [k for k in range(1, total + 1) if plain_line(k, total)] == expected


def test_finetune_with_zero_steps_gives_back_the_starting_network(sim, tmp_path):
    from trmd_cli.models.weights import load_weights

    out = tmp_path / "same.safetensors"
    r = runner.invoke(app, ["finetune", str(sim), "-o", str(out), "--steps", "0",
                            "--threads", "1"])
    assert r.exit_code == 0, r.output
    a, _ = load_weights(out)
    b, _ = load_weights(None)
    for (name, p), q in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        # saved as float16, as the shipped file is
        assert torch.equal(p, q), name


def test_overwrite_leaves_no_picture_of_other_weights_beside_new_ones(sim, tmp_path):
    out = tmp_path / "w.safetensors"
    (tmp_path / "w.png").write_bytes(b"an earlier run's before/after picture")
    r = runner.invoke(app, ["finetune", str(sim), "-o", str(out), "--steps", "0",
                            "--holdout", "0", "--threads", "1", "--overwrite"])
    assert r.exit_code == 0, r.output
    assert out.is_file() and not (tmp_path / "w.png").exists()


def test_without_a_motion_to_learn_from_it_stops_before_training(sim):
    from trmd_cli.train.finetune import finetune

    # a contrast gain no motion reaches: every window untrusted
    with pytest.raises(InputError, match="nothing to fine-tune on"):
        finetune([sim], config=FinetuneConfig(min_confidence=1e6, steps=1, crop=32))
    result, notes = finetune([sim], config=FinetuneConfig(
        min_confidence=1e6, steps=1, crop=32, batch_size=1,
        losses={"reblur": 1.0, "event_consistency": 0.1}), threads=1)
    assert result.trusted == 0
    assert any("only event_consistency train" in n for n in notes), notes


@pytest.mark.parametrize("args, names, needle", [
    (["-o", "{d}/w.pt"], "w.pt", "safetensors"),
    (["-o", "{d}/w.safetensors", "--loss", "warp"], "--loss", "NAME=WEIGHT"),
    (["-o", "{d}/w.safetensors", "--loss", "middle=1"], "middle", "sharp frames"),
    (["-o", "{d}/w.safetensors", "--contrast", "-1"], "--contrast", "positive"),
    (["-o", "{d}/w.safetensors", "--parts", "refine,nope", "--steps", "1"], "nope",
     "its parts: .*refine"),
])
def test_bad_options_give_one_line(sim, tmp_path, args, names, needle):
    args = [a.replace("{d}", str(tmp_path)) for a in args]
    r = runner.invoke(app, ["finetune", str(sim), *args])
    assert_one_error_line(r, names, needle)
    assert not list(tmp_path.iterdir())


def test_an_existing_output_is_refused_before_any_work(tuned, sim):
    out, _ = tuned
    before = out.read_bytes()
    r = runner.invoke(app, ["finetune", str(sim), "-o", str(out), "--steps", "1"])
    assert_one_error_line(r, out.name, "exists")
    assert out.read_bytes() == before


def test_several_recordings_train_together(sim, tmp_path):
    import shutil

    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    shutil.copy(sim, a)
    shutil.copy(sim, b)
    out = tmp_path / "w" / "ab.safetensors"
    out.parent.mkdir()
    r = runner.invoke(app, ["finetune", str(a), str(b), "-o", str(out), "--steps", "1",
                            "--crop", "32", "--batch-size", "1", "--threads", "1"])
    assert r.exit_code == 0, r.output
    info = json.loads(runner.invoke(app, ["info", str(out), "--json"]).stdout)["finetune"]
    assert info["inputs"] == ["a.h5", "b.h5"]
    assert info["windows"] + info["held_out"] == 8


def test_binned_events_train_with_the_motion_of_their_bins(tmp_path):
    """A camera shake binned 18 per exposure (no event times, as LEDVDI ships its data): the
    network's inputs are what `deblur` gives it on bins, the motion comes from the bins and
    agrees with the one the raw events give."""
    from tests.helpers.bins import write_binned_set
    from trmd_cli.edi import PixelEvents
    from trmd_cli.methods import EdiMethod
    from trmd_cli.motion.cmax import estimate_motion
    from trmd_cli.read.base import Frame
    from trmd_cli.train.finetune import _binned_window
    from trmd_cli.voxel import event_bins, scer_from_bins

    seq = make_sequence(texture(200, 260, seed=4), n=3, size=(W, H), exposure_us=20_000,
                        frames=2, rng=np.random.default_rng(2),
                        sensor=SensorConfig.clean(0.3, eps=0.001),
                        motion=MotionRanges(translation_px=12, rotation_deg=0, scale=0.0,
                                            perspective=0.0))
    frames = [type("F", (), {"blurry": seq.blurry[k], "bins": event_bins(
        seq.events, e, 18, window=PixelEvents.build(seq.events, e)).astype(np.int16)})()
        for k, e in enumerate(seq.exposures)]
    cfg = FinetuneConfig()
    win = _binned_window(frames[0].bins, Frame(seq.blurry[0], None, 0, "f0"), 3,
                         EdiMethod(3, None), cfg)
    np.testing.assert_array_equal(win.voxels, scer_from_bins(
        frames[0].bins.reshape(6, 3, H, W).sum(1).astype(np.float32)))
    assert win.levels is None and win.trusted
    raw = estimate_motion(seq.events, seq.exposures[0], None)
    ys, xs = np.mgrid[0:H:8, 0:W:8].astype(np.float64)
    for u in (0.0, 1.0):
        a = np.stack(win.motion.to_middle(np.array(u), xs, ys))
        b = np.stack(raw.to_middle(np.array(u), xs, ys))
        epe = np.hypot(*(a - b)).mean()  # 12 px of shake over the exposure
        assert epe < 0.75, (u, epe)

    images, bins = write_binned_set(tmp_path / "set", frames, fmt="npz")
    out = tmp_path / "w.safetensors"
    r = runner.invoke(app, ["finetune", str(images), str(bins), "-o", str(out), "--steps", "1",
                            "--crop", "32", "--batch-size", "1", "--threads", "1"])
    assert r.exit_code == 0, r.output
    assert "spread evenly over each bin" in r.stderr
    d = runner.invoke(app, ["deblur", str(images), str(bins), "-o", str(tmp_path / "d"),
                            "--weights", str(out), "--threads", "1"])
    assert d.exit_code == 0, d.output


def test_only_the_named_parts_change(sim, tmp_path):
    from trmd_cli.models.weights import load_weights

    out = tmp_path / "head.safetensors"
    r = runner.invoke(app, ["finetune", str(sim), "-o", str(out), "--steps", "2", "--crop",
                            "32", "--batch-size", "2", "--parts", "refine,head", "--threads",
                            "1"])
    assert r.exit_code == 0, r.output
    tuned_net, _ = load_weights(out)
    start, _ = load_weights(None)
    changed = {n.split(".")[0] for (n, p), q in zip(tuned_net.named_parameters(),
                                                     start.parameters(), strict=True)
               if not torch.equal(p, q)}
    assert changed and changed <= {"refine", "head"}, changed
