"""PSNR and SSIM against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from trmd_cli.errors import ShapeError
from trmd_cli.metrics import gaussian_window, psnr, psnr_per_item, ssim


def test_psnr_of_constant_offset_is_20_db_for_0_1():
    a = np.full((16, 16), 0.5, np.float32)
    # MSE = 0.01 → 10·log10(1 / 0.01) = 20 dB
    assert psnr(a, a + 0.1) == pytest.approx(20.0, abs=1e-4)
    assert psnr(torch.from_numpy(a), torch.from_numpy(a - 0.1)) == pytest.approx(20.0, abs=1e-4)


def test_psnr_data_range_and_identical():
    a = np.zeros((4, 4))
    assert psnr(a, a + 1.0, data_range=255.0) == pytest.approx(20 * math.log10(255.0))
    assert psnr(a, a) == math.inf


def test_psnr_per_item_matches_scalar_psnr():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(3, 2, 8, 8, generator=g)
    b = (a + 0.05 * torch.randn(3, 2, 8, 8, generator=g)).clamp(0, 1)
    per = psnr_per_item(a, b)
    assert per.shape == (3,)
    for i in range(3):
        assert float(per[i]) == pytest.approx(psnr(a[i], b[i]), abs=1e-4)


def test_psnr_shape_mismatch_raises():
    with pytest.raises(ShapeError):
        psnr(np.zeros((4, 4)), np.zeros((4, 5)))


def test_ssim_identical_is_one():
    rng = np.random.default_rng(0)
    a = rng.random((32, 40)).astype(np.float32)
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    assert ssim(torch.from_numpy(a), torch.from_numpy(a)) == pytest.approx(1.0, abs=1e-12)


def test_ssim_of_two_constants_is_the_luminance_term():
    # zero variances: the contrast-structure term is C2/C2 = 1, SSIM = (2ab+C1)/(a²+b²+C1)
    a, b = 0.3, 0.6
    c1 = (0.01 * 1.0) ** 2
    expected = (2 * a * b + c1) / (a * a + b * b + c1)
    x, y = np.full((20, 20), a), np.full((20, 20), b)
    assert ssim(x, y) == pytest.approx(expected, rel=1e-9)
    assert ssim(torch.from_numpy(x), torch.from_numpy(y)) == pytest.approx(expected, rel=1e-9)


def test_ssim_of_negated_pattern_is_negative_structure():
    # a = m + d, b = m − d with d zero-mean in every window: the means agree, cov = −var,
    # so SSIM = (−2σ² + C2)/(2σ² + C2) per pixel with σ² the windowed variance of d
    y, x = np.mgrid[0:33, 0:33]
    d = 0.2 * ((x + y) % 2 * 2 - 1)  # checkerboard ±0.2
    a, b = 0.5 + d, 0.5 - d
    c2 = 0.03 ** 2
    w = gaussian_window()
    # the windowed mean of a checkerboard is not exactly 0: compute σ² and μ exactly per window
    k = 11
    vals = []
    for i in range(33 - k + 1):
        for j in range(33 - k + 1):
            pa, pb = a[i:i + k, j:j + k], b[i:i + k, j:j + k]
            ma, mb = (w * pa).sum(), (w * pb).sum()
            va = (w * pa * pa).sum() - ma * ma
            vb = (w * pb * pb).sum() - mb * mb
            cov = (w * pa * pb).sum() - ma * mb
            c1 = 0.01 ** 2
            vals.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma * ma + mb * mb + c1)
                                                              * (va + vb + c2)))
    assert ssim(a, b) == pytest.approx(np.mean(vals), rel=1e-9)
    assert ssim(a, b) < -0.9


def test_ssim_rgb_averages_channels_and_window_sums_to_one():
    rng = np.random.default_rng(1)
    a = rng.random((24, 24, 3))
    b = np.clip(a + 0.1 * rng.standard_normal(a.shape), 0, 1)
    per = [ssim(a[..., c], b[..., c]) for c in range(3)]
    assert ssim(a, b) == pytest.approx(np.mean(per), rel=1e-12)
    assert gaussian_window().sum() == pytest.approx(1.0)
    with pytest.raises(ShapeError):
        ssim(np.zeros((8, 8)), np.zeros((8, 8)))
