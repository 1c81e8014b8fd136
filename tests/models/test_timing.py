"""Sub-bin timing (``voxel.scer_levels``) and networks that take it (``timing``): levels by
hand, exact on a constant-rate ramp where counts are not, within a step of the counts, never
time-reversed by the augmentation; a grown network computes what its old weights computed;
the estimator, the pipeline and training pass the levels through."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from tests.helpers.training import make_image_folder, recipe
from trmd_cli.events import EventStream, Exposure
from trmd_cli.models import RENetInputs, count_macs, create_model
from trmd_cli.models.estimator import TrmdEstimator
from trmd_cli.models.grow import TIMING_INPUTS, load_grown
from trmd_cli.models.weights import load_weights, save_weights
from trmd_cli.train.data import build_data
from trmd_cli.train.loop import train
from trmd_cli.train.recipe import apply_overrides
from trmd_cli.voxel import scer_levels, scer_voxels


def _one_pixel(ts, ps, width: int = 2) -> EventStream:
    ts = np.asarray(ts, np.int64)
    return EventStream(np.zeros(len(ts), np.uint16), np.zeros(len(ts), np.uint16), ts,
                       np.asarray(ps, np.int8), width, 1)


# --------------------------------------------------------------------------------------------
# scer_levels


@pytest.mark.parametrize("ts, ps, expected", [
    # instants 0, 10 … 60, middle 30. At each event Λ is the count reached (1 at t = 10, 2 at
    # 30), linear in between (1.5 at 20), half-way to the first event before it (0.5), the
    # count reached after the last (2)
    ([10, 30], [1, 1], [-1.5, -1.5, -0.5, 0.0, 0.0, 0.0]),
    # one event: half a step before it, the full step after
    ([15], [1], [-0.5, -0.5, 0.0, 0.0, 0.0, 0.0]),
    # up, up, down: levels 1 (t=5), 2 (25), 1 (45); Λ(0) = 0.5, Λ(10) = 1.25, Λ(20) = 1.75,
    # Λ(30) = 1.75 (a quarter of the way down), Λ(40) = 1.25, then 1
    ([5, 25, 45], [1, 1, -1], [-1.25, -0.5, 0.0, -0.5, -0.75, -0.75]),
])
def test_levels_by_hand(ts, ps, expected):
    lv = scer_levels(_one_pixel(ts, ps), Exposure(0, 60), 3)
    assert lv.shape == (6, 1, 2) and lv.dtype == np.float32
    np.testing.assert_allclose(lv[:, 0, 0], expected, atol=1e-6)
    assert not lv[:, 0, 1].any()  # a pixel without events


def test_levels_are_exact_on_a_ramp_where_counts_are_not():
    # an ON event every 300 µs from t = 50: log intensity rising at 1/300 steps per µs
    ts = np.arange(50, 6000, 300)
    ev = _one_pixel(ts, np.ones(len(ts)))
    ex = Exposure(0, 6000)
    lv = scer_levels(ev, ex, 3)[:, 0, 0]
    counts = scer_voxels(ev, ex, 3)[:, 0, 0]
    inner = [1, 2, 3, 4]  # instants 1000 … 5000 (k = 1, 2, 4, 5): between two events
    ramp = np.array([(k - 3) * 1000 / 300 for k in (0, 1, 2, 4, 5, 6)])
    np.testing.assert_allclose(lv[inner], ramp[inner], atol=1e-5)
    assert np.abs(counts[inner] - ramp[inner]).max() > 0.3  # the staircase is off


def _random_stream(seed: int, w: int = 9, h: int = 7, per_px: float = 6.0, t1: int = 6000):
    rng = np.random.default_rng(seed)
    k = int(w * h * per_px)
    # odd timestamps: none exactly on an instant (multiples of 1000)
    t = np.sort(rng.choice(np.arange(1, t1, 2), size=k, replace=False))
    return EventStream(rng.integers(0, w, k).astype(np.uint16),
                       rng.integers(0, h, k).astype(np.uint16), t.astype(np.int64),
                       rng.choice(np.array([-1, 1], np.int8), k), w, h)


def test_levels_stay_within_a_step_of_the_counts():
    # Λ differs from the count only by where, within the step it is taking, the level is
    ev = _random_stream(3)
    ex = Exposure(0, 6000)
    diff = scer_levels(ev, ex, 3) - scer_voxels(ev, ex, 3)
    assert np.abs(diff).max() < 2.0 and np.abs(diff).mean() < 0.6
    assert np.abs(diff).max() > 0.3


def test_augmentation_never_time_reverses_samples_with_levels():
    from trmd_cli.train.data import augment_item

    v = torch.arange(6, dtype=torch.float32).view(6, 1, 1).expand(6, 4, 4).contiguous()
    item = {"blurry": torch.zeros(1, 4, 4), "voxels": v, "levels": v + 0.5,
            "sharp": torch.zeros(7, 1, 4, 4)}
    seen_plain = set()
    for seed in range(40):
        out = augment_item(item, np.random.default_rng(seed))
        assert out["voxels"][:, 0, 0].tolist() == [0, 1, 2, 3, 4, 5]  # time order kept
        torch.testing.assert_close(out["levels"], out["voxels"] + 0.5)
        plain = augment_item({k: x for k, x in item.items() if k != "levels"},
                             np.random.default_rng(seed))
        seen_plain.add(plain["voxels"][0, 0, 0].item())
    assert seen_plain == {0.0, 5.0}  # without levels, about half the draws reverse time


def test_levels_ignore_events_outside_the_window_and_check_n():
    ev = _one_pixel([-50, 10, 30, 90], [1, 1, 1, 1])
    inside = _one_pixel([10, 30], [1, 1])
    np.testing.assert_array_equal(scer_levels(ev, Exposure(0, 60), 3),
                                  scer_levels(inside, Exposure(0, 60), 3))
    assert not scer_levels(_one_pixel([], []), Exposure(0, 60), 3).any()
    with pytest.raises(Exception, match="N must be"):
        scer_levels(inside, Exposure(0, 60), 0)


# --------------------------------------------------------------------------------------------
# The network


def _trained_like(**kw) -> torch.nn.Module:
    torch.manual_seed(1)
    net = create_model("test_trmd", prior="edi_c", **kw)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.2 * torch.randn_like(p))
    return net.eval()


def _inputs(b: int = 2, h: int = 21, w: int = 30):
    g = torch.Generator().manual_seed(5)
    vox = torch.randint(-4, 5, (b, 6, h, w), generator=g).float()
    return torch.rand(b, 1, h, w, generator=g), vox, vox + torch.rand(vox.shape, generator=g) - 0.5


@pytest.mark.parametrize("refine", [0, 2])
def test_grown_timing_network_computes_what_the_weights_computed(refine):
    old = _trained_like(refine=refine)
    new = create_model("test_trmd", prior="edi_c", refine=refine, timing=True).eval()
    grown = load_grown(new, old.state_dict())
    assert sorted(grown.names) == sorted(TIMING_INPUTS) == sorted(grown.timing)
    blurry, vox, levels = _inputs()
    c = torch.tensor([0.2, 0.3])
    x = RENetInputs(blurry, vox, levels=levels, contrast=c)
    with torch.no_grad():
        torch.testing.assert_close(new(x), old(x), atol=1e-6, rtol=0)
    # and the new inputs matter once their weights move
    with torch.no_grad():
        new.event_fe.conv1[0].weight[:, -3:] += 0.1
        assert not torch.allclose(new(x), old(x))


def test_timing_needs_a_prior_and_the_right_channels():
    with pytest.raises(Exception, match="timing needs a prior"):
        create_model("test_trmd", timing=True)
    net = create_model("test_trmd", prior="edi_c", timing=True).eval()
    blurry, vox, levels = _inputs()
    with pytest.raises(Exception, match="sub-bin timing"):
        net(RENetInputs(blurry, vox, contrast=0.2))  # the counts alone
    with pytest.raises(Exception, match="levels has shape"):
        net(RENetInputs(blurry, vox, levels=levels[:, :4], contrast=0.2))
    partial = _trained_like().state_dict()
    partial["head.weight"] = net.state_dict()["head.weight"]
    with pytest.raises(RuntimeError, match="lack the timing"):
        load_grown(net, partial)


def test_macs_grow_by_the_timing_inputs_only():
    a = create_model("trmd_small_prior", timing=False)
    b = create_model("trmd_small_prior")
    h, w = 64, 80
    # blur_fe.conv1: +1 input (5×5, 8 out); event_fe.conv1: +12 inputs (5×5, 8 out);
    # head: +13 inputs (1×1, 6 out) — per pixel
    extra = (1 * 8 * 25 + 12 * 8 * 25 + 13 * 6) * h * w
    assert count_macs(b, h, w) - count_macs(a, h, w) == extra


def test_estimator_and_weights_round_trip(tmp_path):
    net = _trained_like(timing=True)
    path = save_weights(tmp_path / "w.safetensors", net, half=False)
    back, _ = load_weights(path)
    assert back.needs.timing and back.args["timing"] is True
    est = TrmdEstimator.load(path, device="cpu")
    assert est.needs_timing
    rng = np.random.default_rng(0)
    blurry = rng.random((21, 30)).astype(np.float32)
    vox = rng.integers(-3, 4, (6, 21, 30)).astype(np.float32)
    levels = vox + rng.uniform(-0.5, 0.5, vox.shape).astype(np.float32)
    a = est(blurry, vox, 0.25, levels)
    b = est(blurry, vox, 0.25, vox)  # binned data: the counts stand in for the levels
    np.testing.assert_allclose(est(blurry, vox, 0.25), b)
    assert not np.allclose(a, b)
    np.testing.assert_allclose(a.mean(0), blurry, atol=1e-5)  # Eq. 11 still holds
    with pytest.raises(Exception, match="levels have shape"):
        est(blurry, vox, 0.25, levels[:4])


# --------------------------------------------------------------------------------------------
# Training


def _images(tmp_path):
    return make_image_folder(tmp_path / "imgs", 3)


def test_training_data_carries_levels_only_for_timing_networks(tmp_path):
    imgs = _images(tmp_path)
    base = ["data.length=6", "data.val_fraction=0.0", "data.crop=24",
            "model.args={prior='edi_c', timing=true}"]
    item = build_data([imgs], recipe(*base)).train[2]
    assert item["levels"].shape == item["voxels"].shape == (6, 24, 24)
    assert "levels" not in build_data([imgs], recipe(*base[:3])).train[2]


def test_training_grows_timing_into_a_run_without_it(tmp_path):
    imgs = _images(tmp_path)
    base = ["data.length=8", "data.val_fraction=0.0", "data.crop=24", "train.val_every=100",
            "model.args={prior='edi_c'}"]
    train([imgs], recipe=recipe(*base, "train.steps=2"), run_dir=tmp_path / "a")
    grow = apply_overrides(recipe(*base), ["model.args={prior='edi_c', timing=true}",
                                           "optim.lr=1e-12", "optim.min_lr=0.0",
                                           "train.steps=1"])
    res = train([imgs], recipe=grow, run_dir=tmp_path / "b",
                init_weights=tmp_path / "a" / "checkpoint.safetensors")
    assert any("no timing inputs" in n for n in res.notes)
    assert not any("identity" in n for n in res.notes)
    a = load_file(str(tmp_path / "a" / "checkpoint.safetensors"))
    b = load_file(str(tmp_path / "b" / "checkpoint.safetensors"))
    for k, v in a.items():  # every old tensor carried over, the widened ones as a slice
        if k.startswith("model/") and v.is_floating_point() and "running" not in k:
            torch.testing.assert_close(b[k][:, :v.shape[1]] if b[k].shape != v.shape else b[k],
                                       v, atol=1e-6, rtol=0, msg=k)
    assert b["model/head.weight"].shape[1] > a["model/head.weight"].shape[1]


def test_eval_on_binned_data_says_the_timing_inputs_get_counts(tmp_path):
    from tests.helpers.training import make_gopro_h5
    from trmd_cli.evaluate import evaluate_dataset

    weights = save_weights(tmp_path / "w.safetensors", _trained_like(timing=True), half=False)
    data = make_gopro_h5(tmp_path / "g.h5", k=2)
    rep = evaluate_dataset(data, ("trmd",), n=3, weights=weights)
    assert any("timing inputs get the counts" in n for n in rep.notes)
    assert np.isfinite(rep.methods[0].mean("psnr_mid"))
    plain = save_weights(tmp_path / "p.safetensors", _trained_like(), half=False)
    rep = evaluate_dataset(data, ("trmd",), n=3, weights=plain)
    assert not any("timing" in n for n in rep.notes)


def test_pipeline_hands_the_levels_to_a_timing_network(tmp_path):
    from trmd_cli.methods import TrmdMethod
    from trmd_cli.simulate import make_sample

    rng = np.random.default_rng(2)
    image = np.clip(rng.random((90, 120)), 0.05, 1).astype(np.float32)
    s = make_sample(image, size=(48, 40), rng=rng)
    weights = save_weights(tmp_path / "w.safetensors", _trained_like(timing=True), half=False)
    method = TrmdMethod(3, weights, device="cpu", contrast=0.25)
    # the network's frames, before their ghosts are checked against the events
    got = method.grid_frames(s.blurry, s.events, s.exposure,
                             method.prepare(s.blurry, s.events, s.exposure))
    est = method.model
    vox = scer_voxels(s.events, s.exposure, 3)
    want = est(s.blurry, vox, 0.25, scer_levels(s.events, s.exposure, 3))
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert not np.allclose(got, est(s.blurry, vox, 0.25))  # the levels were used
