"""Two-stage reconstruction (Eq. 11–12): hand-computed values, mean = B, round trips."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from trmd_cli.errors import InputError, ShapeError
from trmd_cli.reconstruct import middle_index, reconstruct, residuals_from_latent


def test_hand_computed_n1():
    # B = 0.5, R(0) = -0.3, R(2) = 0.6 → L(1) = 0.5 - 0.3/3 = 0.4, L(0) = 0.1, L(2) = 1.0
    b = np.full((1, 1, 1), 0.5, np.float32)
    r = np.array([-0.3, 0.6], np.float32).reshape(2, 1, 1, 1)
    out = reconstruct(b, r)
    assert out.shape == (3, 1, 1, 1)
    np.testing.assert_allclose(out.ravel(), [0.1, 0.4, 1.0], atol=1e-6)


def test_zero_residuals_give_blurry_everywhere():
    rng = np.random.default_rng(0)
    b = rng.random((3, 5, 7)).astype(np.float32)
    out = reconstruct(b, np.zeros((4, 3, 5, 7), np.float32))
    for k in range(5):
        np.testing.assert_array_equal(out[k], b)


@pytest.mark.parametrize("n", [1, 3, 5])
def test_mean_equals_blurry_numpy(n):
    rng = np.random.default_rng(n)
    b = rng.random((2, 1, 9, 11)).astype(np.float32)
    r = rng.normal(0, 0.5, (2, 2 * n, 1, 9, 11)).astype(np.float32)
    out = reconstruct(b, r)
    assert out.shape == (2, 2 * n + 1, 1, 9, 11)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out.mean(axis=1), b, atol=1e-6)
    # values outside [0, 1] are kept: clipping is the writer's job
    assert out.min() < 0 or out.max() > 1


@pytest.mark.parametrize("n", [1, 3])
def test_mean_equals_blurry_torch(n):
    g = torch.Generator().manual_seed(n)
    b = torch.rand(2, 3, 6, 4, generator=g, dtype=torch.float64)
    r = torch.randn(2, 2 * n, 3, 6, 4, generator=g, dtype=torch.float64)
    out = reconstruct(b, r)
    assert isinstance(out, torch.Tensor) and out.shape == (2, 2 * n + 1, 3, 6, 4)
    torch.testing.assert_close(out.mean(dim=1), b, atol=1e-12, rtol=0)


def test_residuals_are_differences_to_middle():
    out = reconstruct(np.zeros((1, 1, 1), np.float32),
                      np.array([1.0, 2.0, 3.0, 4.0], np.float32).reshape(4, 1, 1, 1))
    mid = out[2]
    np.testing.assert_allclose((out[[0, 1, 3, 4]] - mid).ravel(), [1, 2, 3, 4], atol=1e-6)


def test_numpy_and_torch_agree():
    rng = np.random.default_rng(3)
    b = rng.random((1, 8, 8)).astype(np.float32)
    r = rng.normal(size=(6, 1, 8, 8)).astype(np.float32)
    np.testing.assert_allclose(reconstruct(b, r),
                               reconstruct(torch.from_numpy(b), torch.from_numpy(r)).numpy(),
                               atol=1e-6)


@pytest.mark.parametrize("use_torch", [False, True])
def test_round_trip_latent_residuals_latent(use_torch):
    rng = np.random.default_rng(7)
    latent = rng.random((2, 7, 3, 5, 6)).astype(np.float32)
    if use_torch:
        latent = torch.from_numpy(latent)
    res = residuals_from_latent(latent)
    assert tuple(res.shape) == (2, 6, 3, 5, 6)
    again = reconstruct(latent.mean(-4), res)
    np.testing.assert_allclose(np.asarray(again), np.asarray(latent), atol=1e-6)


def test_residuals_from_latent_values():
    latent = np.arange(5, dtype=np.float32).reshape(5, 1, 1, 1) * 10  # L(k) = 10k, N = 2
    np.testing.assert_array_equal(residuals_from_latent(latent).ravel(), [-20, -10, 10, 20])


def test_gradient_flows_through_torch():
    b = torch.rand(1, 4, 4, dtype=torch.float64, requires_grad=True)
    r = torch.randn(2, 1, 4, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(reconstruct, (b, r))


def test_dtype_promotion():
    b = torch.rand(1, 2, 2)
    r = torch.zeros(2, 1, 2, 2, dtype=torch.float16)
    out = reconstruct(b, r)
    assert out.dtype == torch.float32
    torch.testing.assert_close(out[1], b)  # the frame is not rounded to float16
    assert reconstruct(b.numpy(), r.numpy()).dtype == np.float32


def test_inputs_not_mutated():
    b = np.ones((1, 2, 2), np.float32)
    r = np.ones((2, 1, 2, 2), np.float32)
    b0, r0 = b.copy(), r.copy()
    reconstruct(b, r)
    residuals_from_latent(np.ones((3, 1, 2, 2), np.float32))
    np.testing.assert_array_equal(b, b0)
    np.testing.assert_array_equal(r, r0)


def test_errors():
    b = np.zeros((1, 4, 4), np.float32)
    with pytest.raises(ShapeError):
        reconstruct(b, np.zeros((2, 1, 4, 5), np.float32))  # W differs
    with pytest.raises(ShapeError):
        reconstruct(b, np.zeros((2, 3, 4, 4), np.float32))  # C differs
    with pytest.raises(ShapeError):
        reconstruct(np.zeros((2, 1, 4, 4), np.float32), np.zeros((3, 2, 1, 4, 4), np.float32))
    with pytest.raises(InputError, match="even"):
        reconstruct(b, np.zeros((3, 1, 4, 4), np.float32))
    with pytest.raises(InputError, match="both"):
        reconstruct(torch.zeros(1, 4, 4), np.zeros((2, 1, 4, 4), np.float32))
    with pytest.raises(InputError, match="odd"):
        residuals_from_latent(np.zeros((4, 1, 2, 2), np.float32))
    with pytest.raises(ShapeError):
        residuals_from_latent(np.zeros((3, 2, 2), np.float32))
    assert middle_index(7) == 3
