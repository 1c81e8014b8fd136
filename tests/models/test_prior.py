"""The EDI prior (models/prior.py) and RE-Net given it (prior="edi")."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from trmd_cli.edi import EdiEvents
from trmd_cli.errors import InputError
from trmd_cli.events import Exposure, make_stream
from trmd_cli.models import RENetInputs, create_model
from trmd_cli.models.prior import MAX_LOG_RATIO, edi_prior
from trmd_cli.models.weights import load_weights, save_weights
from trmd_cli.reconstruct import reconstruct
from trmd_cli.voxel import scer_voxels


def test_hand_computed_n1():
    # N = 1: voxels V(0) = a, V(2) = b; L(1) = B / ((e^{ca} + 1 + e^{cb}) / 3)
    a, b, blur, c = -2.0, 3.0, 0.4, 0.2
    voxels = torch.tensor([a, b]).view(1, 2, 1, 1)
    middle, res = edi_prior(torch.full((1, 1, 1, 1), blur), voxels, (c, 2 * c))
    for j, cc in enumerate((c, 2 * c)):
        mid = blur / ((math.exp(cc * a) + 1 + math.exp(cc * b)) / 3)
        assert middle[0, j, 0, 0, 0].item() == pytest.approx(mid, rel=1e-6)
        assert res[0, j, 0, 0, 0, 0].item() == pytest.approx(mid * (math.exp(cc * a) - 1), rel=1e-6)
        assert res[0, j, 1, 0, 0, 0].item() == pytest.approx(mid * (math.exp(cc * b) - 1), rel=1e-6)


def test_blur_model_holds_for_every_contrast():
    # Eq. 11 with these residuals gives back EDI's middle frame: B − mean_k R(k) = L(N)
    g = torch.Generator().manual_seed(1)
    blurry = torch.rand(2, 3, 9, 11, generator=g)
    voxels = torch.randint(-6, 7, (2, 6, 9, 11), generator=g).float()
    middle, res = edi_prior(blurry, voxels, (0.1, 0.25, 0.4))
    for j in range(3):
        latent = reconstruct(blurry, res[:, j])
        torch.testing.assert_close(latent[:, 3], middle[:, j], rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(latent.mean(1), blurry, rtol=1e-5, atol=1e-6)


def test_ratios_match_the_exact_event_integral():
    # L(k)/L(N) = exp(c·(S(t_k) − S(t_N))), S the event integral of the exact EDI
    w, h, n, c = 3, 2, 3, 0.3
    exposure = Exposure(0, 60_000)
    rng = np.random.default_rng(0)
    t = np.sort(rng.integers(1, 59_999, 40))
    t = t[t % 10_000 != 0]  # no event exactly on an instant: conventions there may differ
    ev = make_stream(rng.integers(0, w, t.size), rng.integers(0, h, t.size), t,
                     rng.choice([-1, 1], t.size), w, h)
    vox = scer_voxels(ev, exposure, n)
    middle, res = edi_prior(torch.full((1, 1, h, w), 0.5), torch.from_numpy(vox)[None], (c,))
    levels = EdiEvents.build(ev, exposure).levels_at(np.arange(2 * n + 1) / (2 * n))
    keep = [k for k in range(2 * n + 1) if k != n]
    expected = np.exp(c * (levels[keep] - levels[n]))
    ratio_prior = (res[0, 0, :, 0] / middle[0, 0, 0] + 1).numpy()
    np.testing.assert_allclose(ratio_prior, expected, rtol=1e-5)


def test_clipped_log_ratio_keeps_values_finite_in_half_precision():
    voxels = torch.tensor([500.0, -500.0]).view(1, 2, 1, 1).half()
    middle, res = edi_prior(torch.ones(1, 1, 1, 1).half(), voxels, (0.5,))
    assert torch.isfinite(middle).all() and torch.isfinite(res).all()
    expected = 1 / ((math.exp(MAX_LOG_RATIO) + 1 + math.exp(-MAX_LOG_RATIO)) / 3)
    assert middle.item() == pytest.approx(expected, rel=2e-3)


def test_renet_with_prior_starts_at_edi():
    torch.manual_seed(0)
    net = create_model("test_trmd", prior="edi", prior_contrasts=(0.1, 0.2, 0.3)).eval()
    g = torch.Generator().manual_seed(2)
    blurry = torch.rand(2, 1, 21, 19, generator=g)
    voxels = torch.randint(-4, 5, (2, 6, 21, 19), generator=g).float()
    _, res = edi_prior(blurry, voxels, (0.1, 0.2, 0.3))
    with torch.no_grad():
        out = net(RENetInputs(blurry, voxels))
        # near-zero random head weights elsewhere: close to EDI at the ladder's second contrast
        assert (out - res[:, 1]).abs().max() < 0.05
        identity = torch.zeros_like(net.head.weight)
        identity[net.head.weight > 0.5] = 1.0
        net.head.weight.copy_(identity)
        net.head.bias.zero_()
        torch.testing.assert_close(net(RENetInputs(blurry, voxels)), res[:, 1], rtol=1e-5,
                                   atol=1e-6)


@pytest.mark.parametrize("channels", [1, 3])
def test_renet_with_prior_shapes_and_gradients(channels):
    net = create_model("test_trmd", n=2, channels=channels, prior="edi")
    blurry = torch.rand(2, channels, 13, 30, requires_grad=True)
    out = net(RENetInputs(blurry, torch.randn(2, 4, 13, 30)))
    assert out.shape == (2, 4, channels, 13, 30)
    out.square().mean().backward()
    assert blurry.grad is not None and torch.isfinite(blurry.grad).all()
    assert all(p.grad is not None for p in net.parameters() if p.requires_grad)


def test_prior_args_recorded_and_round_trip(tmp_path):
    net = create_model("test_trmd", prior="edi", prior_contrasts=(0.15, 0.3)).eval()
    assert net.args["prior"] == "edi" and net.args["prior_contrasts"] == [0.15, 0.3]
    assert "prior" not in create_model("test_trmd").args  # older weights files stay identical
    p = save_weights(tmp_path / "w.safetensors", net, meta={}, half=False)
    loaded, meta = load_weights(p)
    assert loaded.args["prior"] == "edi" and loaded.encoder.contrasts == (0.15, 0.3)
    x = RENetInputs(torch.rand(1, 1, 17, 17), torch.randn(1, 6, 17, 17))
    with torch.no_grad():
        torch.testing.assert_close(loaded(x), net(x), rtol=0, atol=0)


@pytest.mark.parametrize("kwargs", [dict(prior="physics"),
                                    dict(prior="edi", prior_contrasts=(0.2,)),
                                    dict(prior="edi", prior_contrasts=(0.2, -0.1))])
def test_bad_prior_arguments(kwargs):
    with pytest.raises(InputError):
        create_model("test_trmd", **kwargs)
