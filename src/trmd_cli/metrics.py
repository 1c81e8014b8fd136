"""Image quality figures, against ground truth and without it.

Against ground truth: PSNR and SSIM, with data range 1 for [0, 1] images. Both accept numpy
arrays or torch tensors. SSIM follows Wang et al. (2004): an 11×11 Gaussian window with σ = 1.5,
K1 = 0.01, K2 = 0.03, population (not sample) statistics, and only the "valid" part of the
filtered maps (no padding), as in the reference MATLAB code.

Without ground truth (real recordings), figures that let users judge results on their own
camera:

* :func:`sharpness`: mean gradient energy (higher = sharper, but noise counts too: read it
  together with the next one);
* :func:`noise_sigma`: Immerkær's estimate of the σ of white noise (lower = cleaner; smooth
  intensity does not count): a noisy frame's sharpness is partly its noise;
* :func:`consistency`: mean ``|Δlog L − c·E|`` between consecutive frames over pixels that had
  events, with ``E`` the signed event count between the two instants and ``c`` the contrast
  threshold (lower = the frames move the way the events say). EDI builds its frames exactly
  this way, so its figure is ~0 up to clipping: the figure judges methods that do not.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .errors import InputError, ShapeError
from .events import EventStream

__all__ = ["psnr", "psnr_per_item", "ssim", "gaussian_window", "sharpness", "noise_sigma",
           "interval_counts", "consistency_from_counts", "consistency", "LOG_EPS"]

_K1, _K2 = 0.01, 0.03
_WIN, _SIGMA = 11, 1.5
#: floor under intensities before taking logs in :func:`consistency`
LOG_EPS = 1e-3


def _check_pair(a, b) -> None:
    if tuple(a.shape) != tuple(b.shape):
        raise ShapeError(f"images differ in shape: {tuple(a.shape)} vs {tuple(b.shape)}")


def psnr(a, b, data_range: float = 1.0) -> float:
    """PSNR in dB over all elements of two same-shape images; ``inf`` when they are equal."""
    _check_pair(a, b)
    if not (math.isfinite(data_range) and data_range > 0):
        raise InputError(f"data_range must be a positive number, got {data_range}")
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


# --------------------------------------------------------------------------------------------
# Figures without ground truth


def _gray(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image, np.float64)
    return a.mean(axis=-1) if a.ndim == 3 else a


def sharpness(image: np.ndarray) -> float:
    """Mean gradient energy ``mean(∂x I)² + mean(∂y I)²`` with forward differences.

    Args:
        image: (H, W) or (H, W, 3) (colour is averaged to gray first), H, W ≥ 2.
    Returns:
        The energy in (intensity units / pixel)²: ``I = a·x + b·y`` gives ``a² + b²``.
    """
    g = _gray(image)
    if g.ndim != 2 or min(g.shape) < 2:
        raise InputError(f"sharpness needs an (H, W) image with H, W ≥ 2, got {np.shape(image)}")
    dx = np.diff(g, axis=1)
    dy = np.diff(g, axis=0)
    return float(np.mean(dx * dx) + np.mean(dy * dy))


def noise_sigma(image: np.ndarray) -> float:
    """σ of additive white noise, estimated as Immerkær (1996) does.

    The image is filtered with a 3×3 kernel (second differences along both axes) that removes
    smooth shading and edges along the axes; for white noise of σ the filtered values have
    standard deviation 6σ, so ``σ = sqrt(π/2) · mean|filtered| / 6``. Oblique edges and texture
    count a little: compare methods on the same frame rather than reading it as an absolute.

    Args:
        image: (H, W) or (H, W, 3) (colour averaged to gray first), [0, 1] intensity, H, W ≥ 3.
    Returns:
        σ in intensity units.
    """
    g = _gray(image)
    if g.ndim != 2 or min(g.shape) < 3:
        raise InputError(f"noise_sigma needs an (H, W) image with H, W ≥ 3, got "
                         f"{np.shape(image)}")
    # Immerkær's kernel [[1,-2,1],[-2,4,-2],[1,-2,1]] is a second difference along y times one
    # along x: zero on any image f(x) + g(y) (edges along an axis, shading), and on bilinear ones
    f = np.diff(np.diff(g, 2, axis=0), 2, axis=1)
    return float(math.sqrt(math.pi / 2) * np.abs(f).mean() / 6.0)


def interval_counts(events: EventStream, instants_us: Sequence[float]) -> tuple[np.ndarray,
                                                                                 np.ndarray]:
    """Signed event counts between consecutive instants.

    An event at time t belongs to the interval ``(instants[j], instants[j+1]]`` (an event exactly
    at an instant has happened by then, as in :mod:`trmd_cli.edi`).

    Args:
        events: the stream (events outside ``(instants[0], instants[-1]]`` are ignored).
        instants_us: (K,) increasing instants, µs.
    Returns:
        ``(net, active)``: (K−1, H, W) float64 signed counts and (K−1, H, W) bool, True where the
        pixel had at least one event in the interval (also when they cancel out).
    """
    inst = np.asarray(instants_us, np.float64).ravel()
    if len(inst) < 2 or not np.isfinite(inst).all() or (np.diff(inst) <= 0).any():
        raise InputError("consistency needs at least two increasing instants")
    h, w = events.height, events.width
    m = len(inst) - 1
    slot = np.searchsorted(inst, events.t, side="left") - 1
    keep = (slot >= 0) & (slot < m)
    flat = slot[keep] * (h * w) + events.y[keep].astype(np.int64) * w + events.x[keep]
    net = np.bincount(flat, weights=events.p[keep].astype(np.float64), minlength=m * h * w)
    count = np.bincount(flat, minlength=m * h * w)
    return net.reshape(m, h, w), (count > 0).reshape(m, h, w)


def consistency_from_counts(frames: np.ndarray, counts: np.ndarray, contrast: float,
                            active: np.ndarray | None = None, eps: float = LOG_EPS) -> float:
    """Mean ``|log L(k+1) − log L(k) − c·E(k)|`` over the (interval, pixel) pairs in ``active``.

    Args:
        frames: (K, H, W) or (K, H, W, 3) output frames in time order (colour averaged to gray);
            intensities are floored at ``eps`` before the log.
        counts: (K−1, H, W) signed event counts between consecutive frames.
        contrast: c, the log-intensity step of one event.
        active: (K−1, H, W) bool of pixels that had events (default: ``counts != 0``).
    Returns:
        The mean error in log-intensity units; NaN when no pixel had events.
    """
    f = np.asarray(frames)
    g = np.asarray(f, np.float64)
    g = g.mean(axis=-1) if g.ndim == 4 else g
    counts = np.asarray(counts, np.float64)
    if g.ndim != 3 or counts.shape != (g.shape[0] - 1, *g.shape[1:]):
        raise InputError(f"consistency needs frames (K, H, W[, 3]) and counts (K−1, H, W), got "
                         f"{f.shape} and {counts.shape}")
    if not (np.isfinite(contrast) and contrast > 0):
        raise InputError(f"contrast threshold must be a positive number, got {contrast}")
    mask = counts != 0 if active is None else np.asarray(active, bool)
    if not mask.any():
        return math.nan
    logs = np.log(np.maximum(g, eps))
    err = np.abs(np.diff(logs, axis=0) - contrast * counts)
    return float(err[mask].mean())


def consistency(frames: np.ndarray, events: EventStream, instants_us: Sequence[float],
                contrast: float) -> float:
    """Event consistency error of output frames (see :func:`consistency_from_counts`).

    Args:
        frames: (K, H, W) or (K, H, W, 3) frames at ``instants_us`` (K ≥ 2).
        events: the events of the span; ``E(k)`` counts those in ``(t_k, t_{k+1}]``.
        instants_us: (K,) increasing instants of the frames, µs.
        contrast: c used to turn event counts into log-intensity steps.
    Returns:
        Mean ``|Δlog L − c·E|`` over (interval, pixel) pairs with at least one event; NaN when
        there are none. Zero for frames built exactly as ``L(k) = L(0)·exp(c·E(0, k))``.
    """
    if len(frames) != len(instants_us):
        raise InputError(f"{len(frames)} frames for {len(instants_us)} instants")
    net, active = interval_counts(events, instants_us)
    return consistency_from_counts(frames, net, contrast, active)
