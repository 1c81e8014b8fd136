"""Two-stage reconstruction of TRMD (Chen & Yu, TMM 2024, Eq. 11–12): residuals → latent frames.

The blurry frame is the mean of the 2N+1 latent frames, B = Σ_k L(k) / (2N+1). Writing
R(k) = L(k) − L(N) for the residuals predicted by RE-Net gives

    L(N) = B − Σ_{k≠N} R(k) / (2N+1)        (Eq. 11)
    L(k) = L(N) + R(k),  k ≠ N               (Eq. 12)

so the mean of the reconstructed frames equals B exactly, whatever the residuals. One pure
function serves training (torch, differentiable) and inference (numpy or torch); no clipping
here — callers clip to [0, 1] when they write images.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError, ShapeError, check_shape

__all__ = ["reconstruct", "residuals_from_latent", "middle_index"]


def middle_index(num_latent: int) -> int:
    """Index N of the middle frame among 2N+1 latent frames."""
    if num_latent < 3 or num_latent % 2 == 0:
        raise InputError(f"expected an odd number ≥ 3 of latent frames (2N+1), got {num_latent}")
    return num_latent // 2


def _is_torch(x) -> bool:
    return type(x).__module__.startswith("torch")


def reconstruct(blurry, residuals):
    """Latent frames L(0..2N) from the blurry frame and the 2N residuals R(k) = L(k) − L(N).

    Args:
        blurry: (..., C, H, W) numpy array or torch tensor.
        residuals: (..., 2N, C, H, W), the same kind, leading dims equal to blurry's; channel
            j holds k = j for j < N and k = j + 1 for j ≥ N (time order, k = N left out).
    Returns:
        (..., 2N+1, C, H, W) in time order k = 0..2N, same kind as the inputs, in the wider of
        their dtypes; differentiable for tensors. Its mean over the 2N+1 axis equals ``blurry``.
    Raises:
        InputError: numpy mixed with torch, or an odd number of residuals.
        ShapeError: shapes do not agree.

    Example::

        >>> import numpy as np
        >>> b = np.full((1, 2, 2), 0.5, np.float32)
        >>> r = np.stack([np.full((1, 2, 2), v, np.float32) for v in (-0.2, 0.1)])
        >>> [round(float(v), 4) for v in reconstruct(b, r)[:, 0, 0, 0]]
        [0.3333, 0.5333, 0.6333]
    """
    if _is_torch(blurry) != _is_torch(residuals):
        raise InputError("blurry and residuals must both be numpy arrays or both torch tensors")
    check_shape(residuals, ("*", None, "C", "H", "W"), "residuals")
    m = residuals.shape[-4]
    if m == 0 or m % 2:
        raise InputError(f"expected an even number 2N ≥ 2 of residuals, got {m}")
    if blurry.ndim != residuals.ndim - 1 or (
            tuple(blurry.shape[:-3]) + tuple(blurry.shape[-3:])
            != tuple(residuals.shape[:-4]) + tuple(residuals.shape[-3:])):
        raise ShapeError(f"blurry has shape {tuple(blurry.shape)}; residuals of shape "
                         f"{tuple(residuals.shape)} need blurry of shape "
                         f"{tuple(residuals.shape[:-4]) + tuple(residuals.shape[-3:])}")
    n = m // 2
    if _is_torch(residuals):
        import torch

        dtype = torch.promote_types(blurry.dtype, residuals.dtype)
        blurry, residuals = blurry.to(dtype), residuals.to(dtype)
        mid = (blurry - residuals.sum(dim=-4) / (m + 1)).unsqueeze(-4)
        return torch.cat([mid + residuals[..., :n, :, :, :], mid,
                          mid + residuals[..., n:, :, :, :]], dim=-4)
    dtype = np.result_type(blurry, residuals)
    residuals = np.asarray(residuals, dtype)
    mid = np.asarray(blurry, dtype) - residuals.sum(axis=-4) / (m + 1)
    mid = mid[..., None, :, :, :]
    return np.concatenate([mid + residuals[..., :n, :, :, :], mid,
                           mid + residuals[..., n:, :, :, :]], axis=-4)


def residuals_from_latent(latent):
    """Residuals R(k) = L(k) − L(N), k ≠ N, from latent frames: the target of the training loss.

    Args:
        latent: (..., 2N+1, C, H, W) numpy array or torch tensor, time order k = 0..2N.
    Returns:
        (..., 2N, C, H, W), same kind, channel order as :func:`reconstruct` expects.
        ``reconstruct(latent.mean(-4), residuals_from_latent(latent))`` returns ``latent``.
    """
    check_shape(latent, ("*", None, "C", "H", "W"), "latent")
    n = middle_index(latent.shape[-4])
    mid = latent[..., n:n + 1, :, :, :]
    if _is_torch(latent):
        import torch

        return torch.cat([latent[..., :n, :, :, :], latent[..., n + 1:, :, :, :]], dim=-4) - mid
    latent = np.asarray(latent)
    return np.concatenate([latent[..., :n, :, :, :], latent[..., n + 1:, :, :, :]],
                          axis=-4) - mid
