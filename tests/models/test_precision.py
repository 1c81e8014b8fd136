"""Mixed precision: which dtype each setting picks, that the network's output in bfloat16
stays close to float32 while the reconstruction keeps Eq. 11 exact, that training reports and
uses it, and that a wrong choice is one clear error."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import trmd_cli.precision as precision
from tests.helpers.training import read_log, recipe
from trmd_cli.errors import InputError
from trmd_cli.models import create_model
from trmd_cli.models.estimator import TrmdEstimator
from trmd_cli.precision import resolve_precision
from trmd_cli.train.loop import train

CPU = torch.device("cpu")


def test_names_map_to_dtypes(monkeypatch):
    assert resolve_precision("fp32", CPU) is None
    assert resolve_precision("bf16", CPU) is torch.bfloat16
    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: True)
    assert resolve_precision("auto", CPU) is torch.bfloat16
    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: False)
    assert resolve_precision("auto", CPU) is None  # emulated bfloat16 would be slower
    assert resolve_precision("auto", torch.device("cuda")) is torch.float16
    with pytest.raises(InputError, match="CUDA"):
        resolve_precision("fp16", CPU)
    with pytest.raises(InputError, match="unknown precision"):
        resolve_precision("half", CPU)


def test_probe_answers_a_bool():
    assert isinstance(precision.cpu_has_native_bf16(), bool)


def _estimator(prec: str) -> TrmdEstimator:
    torch.manual_seed(3)
    net = create_model("test_trmd", prior="edi_c")
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.1 * torch.randn_like(p))
    return TrmdEstimator(net, precision=prec)


def test_bf16_output_is_close_to_fp32_and_keeps_the_blur_model_exact():
    rng = np.random.default_rng(0)
    blurry = rng.uniform(0.2, 0.8, (24, 40)).astype(np.float32)
    voxels = rng.integers(-3, 4, (6, 24, 40)).astype(np.float32)
    full = _estimator("fp32")(blurry, voxels, 0.25)
    half = _estimator("bf16")
    assert half.precision == "bf16" and _estimator("fp32").precision == "fp32"
    low = half(blurry, voxels, 0.25)
    assert low.dtype == np.float32
    # bfloat16 keeps 8 significant bits: residuals of O(0.1–1) agree to a few 1e-3
    assert np.abs(low - full).max() < 0.03
    assert np.abs(low - full).max() > 0  # it did run in another precision
    # Eq. 11 is computed in float32 from the residuals: the mean frame is B in both
    np.testing.assert_allclose(low.mean(0), blurry, atol=2e-6)
    np.testing.assert_allclose(full.mean(0), blurry, atol=2e-6)


@pytest.mark.parametrize("native", [True, False])
def test_training_uses_bf16_only_where_native(gopro, tmp_path, monkeypatch, native):  # noqa: F811
    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: native)
    seen = []
    real = torch.autocast

    def spy(*args, **kwargs):
        if kwargs.get("enabled", True):
            seen.append(kwargs.get("dtype"))
        return real(*args, **kwargs)

    monkeypatch.setattr(torch, "autocast", spy)
    res = train([gopro], recipe=recipe("train.steps=10", "train.val_every=10"),
                run_dir=tmp_path / "run")
    assert res.steps == 10 and np.isfinite(res.val_psnr_mid)
    # 10 training steps in bfloat16; validation stays float32 so figures compare across runs
    assert seen == ([torch.bfloat16] * 10 if native else [])
    loss = [float(r["loss"]) for r in read_log(tmp_path / "run" / "log.csv")]
    assert loss[-1] < loss[0]


def test_amp_off_keeps_float32(gopro, tmp_path, monkeypatch):  # noqa: F811
    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: True)
    seen = []
    real = torch.autocast
    monkeypatch.setattr(torch, "autocast", lambda *a, **k: (
        seen.append(k.get("dtype")) if k.get("enabled", True) else None, real(*a, **k))[1])
    train([gopro], recipe=recipe("train.steps=2", "train.val_every=2", "train.amp=false"),
          run_dir=tmp_path / "run")
    assert seen == []


def test_attention_logits_stay_finite_under_float16_autocast():
    # a 260×346 frame: K·Qᵀ sums 90k products per logit — beyond float16's 65504
    from trmd_cli.models import channel_cross_attention

    g = torch.Generator().manual_seed(0)
    k, q, v = (3 + torch.rand(1, 4, 260, 346, generator=g) for _ in range(3))
    ref = channel_cross_attention(k, q, v, "spatial")
    with torch.autocast("cpu", dtype=torch.float16):
        low = channel_cross_attention(k, q, v, "spatial")
    assert torch.isfinite(low).all()
    torch.testing.assert_close(low.float(), ref, rtol=5e-3, atol=5e-3)
