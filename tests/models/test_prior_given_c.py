"""The prior around a given threshold (``prior="edi_c"``): the per-sample ladder, the network
that needs c, and every path that must hand it one (estimator, pipeline, training)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from trmd_cli.errors import InputError, ShapeError
from trmd_cli.methods import EdiMethod, TrmdMethod
from trmd_cli.models import RENetInputs, RENetNeeds, create_model
from trmd_cli.models.estimator import TrmdEstimator
from trmd_cli.models.prior import DEFAULT_CONTRASTS, RELATIVE_CONTRASTS, edi_prior
from trmd_cli.models.weights import load_weights, save_weights
from trmd_cli.train.loop import forward


def _inputs(seed: int = 3, b: int = 2, h: int = 15, w: int = 18):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(b, 1, h, w, generator=g),
            torch.randint(-5, 6, (b, 6, h, w), generator=g).float())


def test_per_sample_ladder_equals_one_call_per_sample():
    blurry, voxels = _inputs()
    ladders = torch.tensor([[0.1, 0.2], [0.3, 0.45]])
    mid, res = edi_prior(blurry, voxels, ladders)
    for i in range(2):
        m1, r1 = edi_prior(blurry[i:i + 1], voxels[i:i + 1], ladders[i].tolist())
        torch.testing.assert_close(mid[i:i + 1], m1)
        torch.testing.assert_close(res[i:i + 1], r1)


def test_relative_ladder_keeps_the_fixed_ladders_ratios():
    assert RELATIVE_CONTRASTS[1] == 1.0
    for rel, c in zip(RELATIVE_CONTRASTS, DEFAULT_CONTRASTS):
        assert rel * DEFAULT_CONTRASTS[1] == pytest.approx(c)


def test_given_c_network_is_the_fixed_one_scaled():
    torch.manual_seed(0)
    fixed = create_model("test_trmd", prior="edi").eval()
    given = create_model("test_trmd", prior="edi_c").eval()
    given.load_state_dict(fixed.state_dict())  # same shapes: weights carry over
    assert given.needs == RENetNeeds(contrast=True) and fixed.needs == RENetNeeds()
    blurry, voxels = _inputs()
    with torch.no_grad():
        # c = 0.2 puts the relative ladder exactly on the fixed one
        torch.testing.assert_close(given(RENetInputs(blurry, voxels, contrast=0.2)),
                                   fixed(RENetInputs(blurry, voxels)))
        other = create_model("test_trmd", prior="edi",
                             prior_contrasts=[0.3 * r for r in RELATIVE_CONTRASTS]).eval()
        other.load_state_dict(fixed.state_dict())
        both = given(RENetInputs(blurry, voxels, contrast=torch.tensor([0.2, 0.3])))
        torch.testing.assert_close(both[1:], other(RENetInputs(blurry[1:], voxels[1:])))
        torch.testing.assert_close(both[:1], fixed(RENetInputs(blurry[:1], voxels[:1])))


def test_given_c_network_refuses_missing_or_bad_c():
    net = create_model("test_trmd", prior="edi_c").eval()
    blurry, voxels = _inputs()
    with pytest.raises(InputError, match="contrast threshold"):
        net(RENetInputs(blurry, voxels))
    with pytest.raises(InputError, match="positive"):
        net(RENetInputs(blurry, voxels, contrast=torch.tensor([0.2, -1.0])))
    with pytest.raises(ShapeError, match="batch of 2"):
        net(RENetInputs(blurry, voxels, contrast=torch.tensor([0.2, 0.2, 0.2])))


def test_weights_round_trip_and_estimator_needs_c(tmp_path):
    net = create_model("test_trmd", prior="edi_c").eval()
    p = save_weights(tmp_path / "w.safetensors", net, meta={}, half=False)
    loaded, _ = load_weights(p)
    assert loaded.needs.contrast and loaded.encoder.contrasts == RELATIVE_CONTRASTS
    est = TrmdEstimator(loaded)
    blurry, voxels = _inputs(b=1)
    with pytest.raises(InputError, match="contrast threshold"):
        est(blurry[0, 0].numpy(), voxels[0].numpy())
    out = est(blurry[0, 0].numpy(), voxels[0].numpy(), 0.25)
    with torch.no_grad():
        from trmd_cli.reconstruct import reconstruct
        ref = reconstruct(blurry, net(RENetInputs(blurry, voxels, contrast=0.25)))[0, :, 0]
    ref = ref.numpy()
    np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-6)


def test_pipeline_hands_the_network_edis_threshold(tmp_path, monkeypatch):
    from trmd_cli.simulate import SensorConfig, make_sample

    net = create_model("test_trmd", prior="edi_c").eval()
    p = save_weights(tmp_path / "w.safetensors", net, meta={}, half=False)
    rng = np.random.default_rng(0)
    image = rng.random((80, 96)).astype(np.float32)
    s = make_sample(image, n=3, size=(64, 48), rng=rng, sensor=SensorConfig.clean(0.3))
    seen: list = []
    real = TrmdEstimator.__call__

    def spy(self, blurry, voxels, contrast=None, levels=None):
        seen.append(contrast)
        return real(self, blurry, voxels, contrast, levels)

    monkeypatch.setattr(TrmdEstimator, "__call__", spy)
    given = TrmdMethod(3, p, threads=1, contrast=0.37)(s.blurry, s.events, s.exposure)
    assert seen[-1] == 0.37 and given.contrast == 0.37 and not given.contrast_estimated
    auto = TrmdMethod(3, p, threads=1)(s.blurry, s.events, s.exposure)
    edi_c = EdiMethod(3).prepare(s.blurry, s.events, s.exposure).contrast
    assert seen[-1] == pytest.approx(edi_c) and auto.contrast == pytest.approx(edi_c)
    assert auto.contrast_estimated and auto.frames.shape == (7, 48, 64)


def test_training_forward_jitters_the_true_c(monkeypatch):
    got: list = []

    class Probe(torch.nn.Module):
        def forward(self, inputs):
            got.append(inputs.contrast)
            return torch.zeros(1)

    blurry, voxels = _inputs(b=4)
    batch = {"blurry": blurry, "voxels": voxels,
             "contrast": torch.tensor([0.2, float("nan"), 0.4, 0.3])}
    forward(Probe(), batch, needs=RENetNeeds(contrast=True), fallback_contrast=0.25)
    torch.testing.assert_close(got[-1], torch.tensor([0.2, 0.25, 0.4, 0.3]))
    torch.manual_seed(5)
    forward(Probe(), batch, needs=RENetNeeds(contrast=True), jitter=0.15,
            fallback_contrast=0.25)
    torch.manual_seed(5)
    factor = torch.exp(0.15 * torch.randn(4))
    torch.testing.assert_close(got[-1], torch.tensor([0.2, 0.25, 0.4, 0.3]) * factor)
    forward(Probe(), batch, needs=RENetNeeds())
    assert got[-1] is None


def test_training_without_a_true_threshold_says_which_c_it_used(tmp_path):
    from tests.helpers.training import make_gopro_h5, recipe
    from trmd_cli.train.loop import train

    data = make_gopro_h5(tmp_path / "g.h5", k=8)  # the paper's layout: no threshold stored
    r = recipe("model.name='test_trmd'", "model.args.prior='edi_c'", "train.steps=2",
               "train.val_every=2", "loss.contrast=0.3")
    res = train([data], recipe=r, run_dir=tmp_path / "run")
    assert res.steps == 2 and any("loss.contrast = 0.3" in n for n in res.notes)
