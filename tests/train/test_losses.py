"""Training losses: hand-computed values, what needs ground truth and what does not."""

from __future__ import annotations

import math

import pytest
import torch

from trmd_cli.errors import InputError
from trmd_cli.reconstruct import reconstruct, residuals_from_latent
from trmd_cli.train.losses import LOSSES, full_voxels, penalty, register_loss, total_loss
from trmd_cli.train.recipe import Recipe, apply_overrides, load_recipe

N = 3


def recipe(*overrides: str) -> Recipe:
    return apply_overrides(Recipe(), list(overrides)) if overrides else Recipe()


def sharp_batch(b: int = 2, c: int = 1, h: int = 6, w: int = 5, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    sharp = 0.2 + 0.6 * torch.rand(b, 2 * N + 1, c, h, w, generator=g)
    return {"sharp": sharp, "blurry": sharp.mean(1),
            "voxels": torch.zeros(b, 2 * N, h, w), "contrast": torch.full((b,), 0.2)}


def outputs_for(batch: dict, residuals: torch.Tensor) -> dict:
    return {"residuals": residuals, "latent": reconstruct(batch["blurry"], residuals)}


def test_perfect_residuals_give_zero_supervised_losses():
    batch = sharp_batch()
    out = outputs_for(batch, residuals_from_latent(batch["sharp"]))
    for name in ("residual", "middle", "sequence"):
        for pen in ("mse", "l1", "charbonnier"):
            assert float(LOSSES[name](out, batch, recipe(f"loss.penalty={pen!r}"))) == \
                pytest.approx(0.0, abs=1e-6)


def test_offset_residuals_hand_values():
    # every residual off by δ: residual MSE = δ²; the middle frame moves by −2N·δ/(2N+1)
    batch = sharp_batch()
    d = 0.1
    out = outputs_for(batch, residuals_from_latent(batch["sharp"]) + d)
    r = recipe()
    assert float(LOSSES["residual"](out, batch, r)) == pytest.approx(d * d, rel=1e-5)
    assert float(LOSSES["middle"](out, batch, r)) == pytest.approx((2 * N * d / (2 * N + 1)) ** 2,
                                                                   rel=1e-5)
    total, parts = total_loss(out, batch, r)
    assert set(parts) == {"residual", "middle"}
    assert float(total) == pytest.approx(d * d + (2 * N * d / (2 * N + 1)) ** 2, rel=1e-5)
    # λ from the recipe
    total2, _ = total_loss(out, batch, recipe("loss.middle=3.0"))
    assert float(total2) == pytest.approx(d * d + 3 * (2 * N * d / (2 * N + 1)) ** 2, rel=1e-5)


def test_penalties_on_a_constant_difference():
    diff = torch.full((4, 4), -0.3)
    assert float(penalty(diff, recipe())) == pytest.approx(0.09)
    assert float(penalty(diff, recipe("loss.penalty='l1'"))) == pytest.approx(0.3)
    eps = 0.01
    r = recipe("loss.penalty='charbonnier'", f"loss.charbonnier_eps={eps}")
    assert float(penalty(diff, r)) == pytest.approx(math.sqrt(0.09 + eps * eps) - eps, rel=1e-6)


def test_blur_consistency_is_zero_unless_clipping_bites():
    batch = sharp_batch()
    g = torch.Generator().manual_seed(1)
    small = 0.05 * torch.randn(2, 2 * N, 1, 6, 5, generator=g)
    r = recipe()
    # within [0, 1] the two-stage reconstruction averages to the blurry frame exactly
    assert float(LOSSES["blur_consistency"](outputs_for(batch, small), batch, r)) == \
        pytest.approx(0.0, abs=1e-12)
    # blurry 0.5 everywhere; residuals +0.8 for k = 0, −0.8 for k = 2N (others 0): the mean
    # stays 0.5 but frame 0 is 1.3 → clipped to 1, frame 2N is −0.3 → clipped to 0
    blurry = torch.full((1, 1, 2, 2), 0.5)
    res = torch.zeros(1, 2 * N, 1, 2, 2)
    res[:, 0], res[:, -1] = 0.8, -0.8
    b = {"blurry": blurry, "voxels": torch.zeros(1, 2 * N, 2, 2)}
    clipped_mean = (1.0 + 0.0 + 0.5 * (2 * N - 1)) / (2 * N + 1)
    expected = (clipped_mean - 0.5) ** 2
    assert float(LOSSES["blur_consistency"](outputs_for(b, res), b, r)) == \
        pytest.approx(expected, rel=1e-5)


def event_batch(c_true: float, eps: float, contrast) -> tuple[dict, dict]:
    """Latent frames that obey the event model exactly for integer voxels."""
    g = torch.Generator().manual_seed(2)
    b, h, w = 2, 5, 4
    vox = torch.randint(-3, 4, (b, 2 * N, h, w), generator=g).float()
    mid = 0.3 + 0.4 * torch.rand(b, 1, h, w, generator=g)
    full = full_voxels(vox)  # (B, 2N+1, H, W), V(N) = 0
    latent = ((mid + eps) * torch.exp(c_true * full) - eps).unsqueeze(2)
    batch = {"blurry": latent.mean(1), "voxels": vox}
    if contrast is not None:
        batch["contrast"] = contrast
    return batch, {"latent": latent, "residuals": residuals_from_latent(latent)}


def test_full_voxels_differences_are_the_bin_counts():
    from trmd_cli.voxel import scer_from_bins

    bins = torch.randint(-2, 3, (2 * N, 3, 3)).float()
    full = full_voxels(scer_from_bins(bins)[None])[0]
    assert torch.equal(full[1:] - full[:-1], bins)


def test_event_consistency_zero_for_frames_that_obey_the_events():
    eps = 1e-3
    r = recipe(f"loss.log_eps={eps}")
    batch, out = event_batch(0.25, eps, torch.tensor([0.25, 0.25]))
    assert float(LOSSES["event_consistency"](out, batch, r)) == pytest.approx(0.0, abs=1e-9)


def test_event_consistency_uses_batch_contrast_then_recipe_fallback():
    eps = 1e-3
    batch, out = event_batch(0.25, eps, torch.tensor([0.2, float("nan")]))
    r = recipe(f"loss.log_eps={eps}", "loss.contrast=0.25")
    # item 0 uses c = 0.2 (error 0.05·b_j per step), item 1 falls back to 0.25 (no error)
    full = full_voxels(batch["voxels"])
    bj = full[:, 1:] - full[:, :-1]
    expected = torch.cat([(0.05 * bj[0]).square().flatten(), torch.zeros(bj[1].numel())]).mean()
    got = LOSSES["event_consistency"](out, batch, r)
    assert float(got) == pytest.approx(float(expected), rel=1e-4)
    # no contrast in the batch: the recipe's value for all
    del batch["contrast"]
    assert float(LOSSES["event_consistency"](out, batch, r)) == pytest.approx(0.0, abs=1e-9)


def test_event_consistency_rgb_goes_through_luma():
    eps = 1e-3
    batch, out = event_batch(0.2, eps, None)
    rgb = out["latent"].repeat(1, 1, 3, 1, 1)  # gray as RGB: the luma weights sum to 1
    out3 = {"latent": rgb, "residuals": residuals_from_latent(rgb)}
    r = recipe(f"loss.log_eps={eps}", "loss.contrast=0.2")
    assert float(LOSSES["event_consistency"](out3, batch, r)) == pytest.approx(0.0, abs=1e-6)


def test_unsupervised_losses_need_no_sharp_frames_and_give_gradients():
    batch = sharp_batch()
    del batch["sharp"]
    res = (0.3 * torch.randn(2, 2 * N, 1, 6, 5)).requires_grad_()
    r = recipe("loss.residual=0", "loss.middle=0", "loss.event_consistency=1.0",
               "loss.blur_consistency=1.0")
    total, parts = total_loss(outputs_for(batch, res), batch, r)
    assert set(parts) == {"event_consistency", "blur_consistency"}
    total.backward()
    assert res.grad is not None and float(res.grad.abs().sum()) > 0


def test_supervised_loss_without_sharp_says_what_to_do():
    batch = sharp_batch()
    del batch["sharp"]
    out = outputs_for(batch, torch.zeros(2, 2 * N, 1, 6, 5))
    with pytest.raises(InputError, match="ground-truth sharp") as e:
        total_loss(out, batch, recipe())
    assert "event_consistency" in str(e.value)


def test_a_registered_loss_is_usable_from_a_recipe(tmp_path, monkeypatch):
    monkeypatch.setattr("trmd_cli.train.losses.LOSSES", dict(LOSSES))

    @register_loss("mean_residual")
    def mean_residual(outputs, batch, recipe):
        return outputs["residuals"].mean()

    p = tmp_path / "r.toml"
    p.write_text("[loss]\nmean_residual = 2.0\n")
    r = load_recipe(p)
    batch = sharp_batch()
    out = outputs_for(batch, torch.full((2, 2 * N, 1, 6, 5), 0.25))
    total, parts = total_loss(out, batch, r)
    assert float(total) == pytest.approx(0.5)
    assert list(parts) == ["mean_residual"]
