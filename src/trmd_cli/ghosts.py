"""Ghosts in a network's frames, found and replaced by what the events report.

Between the middle instant and instant k a pixel's log intensity changes by what its events
report, ``c·(S(t_k) − S(t_N))``; EDI's frames obey this by construction, a network's need not.
Under large motion TRMD's end frames keep a faint copy of an edge at its mid-exposure place, or
paint one where the events never swept (double rims, a card's checkerboard seen twice): there
the frame's change from its middle frame and the events' disagree over an area. Where the events
are only noisy they disagree at isolated pixels. So the disagreement (in log intensity) is
smoothed over a few pixels, and where it stays large the frame is replaced by its middle frame
carried to k by the events, ``L(N)·exp(c·ΔS)``, median-filtered over 3×3 pixels so that one
noise event is not taken for a change; elsewhere the network's frame is kept as it is.

On simulated sets (ghost-free, ground truth known) this changes TRMD's sequence PSNR by at most
a few hundredths of a dB (``docs/experiments.md``); on the real ``ledvdi-rotate`` recording it
removes most of the end frames' double copies of the swinging card.
"""

from __future__ import annotations

import numpy as np

from .errors import ShapeError

__all__ = ["GHOST_SIGMA", "GHOST_LOW", "GHOST_HIGH", "carried", "ghost_weight",
           "without_ghosts"]

#: Gaussian σ (px) over which the disagreement is averaged: one noisy event (one pixel) is
#: diluted ≈ 14×, a ghost's edge (a line, or an area) is not
GHOST_SIGMA = 1.5
#: smoothed disagreement (log intensity) below which the network's frame is kept whole …
GHOST_LOW = 0.2
#: … and above which it is replaced whole (linear in between)
GHOST_HIGH = 0.5
#: offset in log(L + eps): dark pixels' noise does not count as a disagreement
_EPS = 0.02


def _luma(frames: np.ndarray) -> np.ndarray:
    if frames.ndim == 4:
        return frames @ np.array([0.299, 0.587, 0.114], np.float32)
    return frames


def carried(frames: np.ndarray, change: np.ndarray, n: int) -> np.ndarray:
    """The middle frame carried to every instant by the events: ``L(N)·exp(change)``, each
    median-filtered over 3×3 pixels. (K, H, W[, 3]) float32."""
    import cv2

    mid = np.maximum(frames[n], 0.0).astype(np.float32)
    factor = np.exp(change.astype(np.float32))
    out = mid[None] * (factor[..., None] if frames.ndim == 4 else factor)
    return np.stack([cv2.medianBlur(np.ascontiguousarray(p), 3) for p in out])


def ghost_weight(frames: np.ndarray, carried_frames: np.ndarray, n: int) -> np.ndarray:
    """Per instant and pixel, how much of the frame is a ghost: (K, H, W) float32 in [0, 1],
    0 at k = N, from how far ``frames`` and ``carried_frames`` (:func:`carried`'s: the events'
    reading) disagree in log intensity."""
    import cv2

    lf = np.log(np.maximum(_luma(frames), 0.0) + np.float32(_EPS))
    lc = np.log(np.maximum(_luma(carried_frames), 0.0) + np.float32(_EPS))
    out = np.zeros(lf.shape, np.float32)
    for k in range(len(frames)):
        if k == n:
            continue
        d = cv2.GaussianBlur(np.abs(lf[k] - lc[k]).astype(np.float32), (0, 0), GHOST_SIGMA)
        out[k] = np.clip((d - GHOST_LOW) / (GHOST_HIGH - GHOST_LOW), 0.0, 1.0)
    return out


def without_ghosts(frames: np.ndarray, change: np.ndarray, n: int) -> np.ndarray:
    """``frames`` with their ghosts replaced by what the events report (see the module).

    Args:
        frames: (2N+1, H, W[, 3]) float32 latent frames, [0, 1] intensity (values outside are
            kept where the frame is kept).
        change: (2N+1, H, W) the events' log-intensity change from the middle instant to each,
            ``c·(S(t_k) − S(t_N))`` (0 at k = N).
        n: N (the middle frame's index), which is returned unchanged.
    Returns:
        (2N+1, H, W[, 3]) float32.
    """
    frames = np.asarray(frames, np.float32)
    if frames.ndim not in (3, 4) or len(frames) != 2 * n + 1 \
            or np.shape(change) != frames.shape[:3]:
        raise ShapeError(f"frames {frames.shape} and changes {np.shape(change)} must be "
                         f"(2N+1, H, W[, 3]) and (2N+1, H, W) with 2N+1 = {2 * n + 1}")
    moved = carried(frames, change, n)
    w = ghost_weight(frames, moved, n)
    if frames.ndim == 4:
        w = w[..., None]
    return frames + w * (moved - frames)
