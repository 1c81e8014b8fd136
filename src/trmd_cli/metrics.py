"""Image quality figures: PSNR and SSIM, with data range 1 for [0, 1] images.

Both accept numpy arrays or torch tensors. SSIM follows Wang et al. (2004): an 11×11 Gaussian
window with σ = 1.5, K1 = 0.01, K2 = 0.03, population (not sample) statistics, and only the
"valid" part of the filtered maps (no padding), as in the reference MATLAB code.
"""

from __future__ import annotations

import math

import numpy as np

from .errors import InputError, ShapeError

__all__ = ["psnr", "psnr_per_item", "ssim", "gaussian_window"]

_K1, _K2 = 0.01, 0.03
_WIN, _SIGMA = 11, 1.5


def _check_pair(a, b) -> None:
    if tuple(a.shape) != tuple(b.shape):
        raise ShapeError(f"images differ in shape: {tuple(a.shape)} vs {tuple(b.shape)}")


def psnr(a, b, data_range: float = 1.0) -> float:
    """PSNR in dB over all elements of two same-shape images; ``inf`` when they are equal."""
    _check_pair(a, b)
    if data_range <= 0:
        raise InputError(f"data_range must be positive, got {data_range}")
    if isinstance(a, np.ndarray):
        diff = a.astype(np.float64) - np.asarray(b, np.float64)
        mse = float(np.mean(diff * diff))
    else:
        mse = float(((a.double() - b.double()) ** 2).mean())
    if mse == 0.0:
        return math.inf
    return 10.0 * math.log10(data_range * data_range / mse)


def psnr_per_item(a, b, data_range: float = 1.0):
    """Torch: PSNR (B,) in dB of each item of (B, ...) tensors (MSE floored at 1e-12)."""
    _check_pair(a, b)
    mse = ((a.double() - b.double()) ** 2).flatten(1).mean(1).clamp_min(1e-12)
    return (10.0 * (data_range * data_range / mse).log10()).float()


def gaussian_window(size: int = _WIN, sigma: float = _SIGMA) -> np.ndarray:
    """(size, size) float64 Gaussian weights summing to 1."""
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2
    g = np.exp(-(x * x) / (2 * sigma * sigma))
    g /= g.sum()
    return np.outer(g, g)


def ssim(a, b, data_range: float = 1.0) -> float:
    """Mean SSIM of two images.

    Args:
        a, b: numpy (H, W) or (H, W, C), or torch (..., H, W) — channels (and leading dims)
            are averaged. H and W must be at least 11.
        data_range: the span of pixel values (1 for [0, 1] images).
    """
    _check_pair(a, b)
    if data_range <= 0:
        raise InputError(f"data_range must be positive, got {data_range}")
    if isinstance(a, np.ndarray):
        a64, b64 = a.astype(np.float64), np.asarray(b, np.float64)
        if a64.ndim == 2:
            a64, b64 = a64[None], b64[None]
        elif a64.ndim == 3:
            a64, b64 = np.moveaxis(a64, -1, 0), np.moveaxis(b64, -1, 0)
        else:
            raise ShapeError(f"ssim takes (H, W) or (H, W, C) arrays, got {a.shape}")
        maps = [_ssim_map_np(x, y, data_range).mean() for x, y in zip(a64, b64, strict=True)]
        return float(np.mean(maps))
    return float(_ssim_map_torch(a, b, data_range).mean())


def _ssim_map_np(x: np.ndarray, y: np.ndarray, data_range: float) -> np.ndarray:
    import cv2

    if min(x.shape) < _WIN:
        raise ShapeError(f"ssim needs images of at least {_WIN}x{_WIN}, got {x.shape}")
    w = gaussian_window()
    r = _WIN // 2

    def filt(img: np.ndarray) -> np.ndarray:
        # cv2 correlates; the window is symmetric. Crop the border: "valid" filtering.
        return cv2.filter2D(img, cv2.CV_64F, w, borderType=cv2.BORDER_REFLECT)[r:-r, r:-r]

    return _ssim_formula(filt(x), filt(y), filt(x * x), filt(y * y), filt(x * y), data_range)


def _ssim_map_torch(x, y, data_range: float):
    import torch
    import torch.nn.functional as F

    if x.ndim < 2 or min(x.shape[-2:]) < _WIN:
        raise ShapeError(f"ssim needs (..., H, W) with H, W ≥ {_WIN}, got {tuple(x.shape)}")
    h, w_ = x.shape[-2:]
    x = x.reshape(-1, 1, h, w_).double()
    y = y.reshape(-1, 1, h, w_).double()
    k = torch.from_numpy(gaussian_window()).to(x.device)[None, None]

    def filt(img):
        return F.conv2d(img, k)

    return _ssim_formula(filt(x), filt(y), filt(x * x), filt(y * y), filt(x * y), data_range)


def _ssim_formula(mx, my, mxx, myy, mxy, data_range: float):
    c1 = (_K1 * data_range) ** 2
    c2 = (_K2 * data_range) ** 2
    vx = mxx - mx * mx
    vy = myy - my * my
    cov = mxy - mx * my
    return ((2 * mx * my + c1) * (2 * cov + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
