"""The EDI prior: EDI's latent frames computed from the SCER voxels alone, in torch.

SCER voxels already hold EDI's event integral at the 2N+1 instants: V(k) = E(N → k), the signed
event count from the middle instant to instant k (V(N) = 0 is dropped). With a contrast
threshold c the latent frames of EDI (Pan et al. 2019) at those instants are

    L(k) = L(N) · exp(c · V(k)),   L(N) = B / mean_k exp(c · V(k)),

the mean being the 2N+1-point rectangle rule — the same blur model as the paper's Eq. 11
(``B = mean_k L(k)``), so ``B − mean_k R(k) = L(N)`` holds exactly for these frames. On the
pinned validation set this coarse EDI, at the true c, is within 0.1 dB (middle) and 0.3 dB
(sequence) of the exact event-by-event EDI.

The threshold is unknown at inference, so the prior is computed for a ladder of contrasts —
fixed (``prior="edi"``) or scaled around an estimate of the threshold given with every frame
(``prior="edi_c"``: the tool estimates it as ``--method edi`` does, training jitters the true
one) — and the network learns how to use them (a per-pixel soft choice, plus everything EDI
does not model: noise, threshold mismatch, the level between two crossings). That gives the
network, from the first step, what it would otherwise have to learn to compute: an exponential
of the event integral and a division by its mean over time.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

__all__ = ["DEFAULT_CONTRASTS", "RELATIVE_CONTRASTS", "MAX_LOG_RATIO", "edi_prior"]

#: the contrast ladder of the prior: spans the 0.1–0.5 range of real and simulated sensors
DEFAULT_CONTRASTS = (0.125, 0.2, 0.3, 0.45)
#: the ladder of ``prior="edi_c"``, as multiples of the given threshold: the same ratios as the
#: fixed ladder around its second rung, so weights trained with one start well with the other
RELATIVE_CONTRASTS = tuple(c / DEFAULT_CONTRASTS[1] for c in DEFAULT_CONTRASTS)
#: |c·V| is clipped here (a factor e⁴ ≈ 55 in intensity): hot pixels and dense noise would
#: otherwise overflow exp() in half precision and dominate the features
MAX_LOG_RATIO = 4.0


def edi_prior(blurry: torch.Tensor, voxels: torch.Tensor,
              contrasts: Sequence[float] | torch.Tensor = DEFAULT_CONTRASTS
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """EDI's middle frame and residuals for each contrast of a ladder.

    Args:
        blurry: (B, C, H, W) blurry frame, [0, 1] intensity.
        voxels: (B, 2N, H, W) SCER voxels, event counts (k ≠ N, time order).
        contrasts: K contrast thresholds (log-intensity units per event), the same for every
            sample, or a (B, K) tensor: a ladder per sample.
    Returns:
        ``(middle, residuals)``: middle (B, K, C, H, W) = L(N) for each contrast; residuals
        (B, K, 2N, C, H, W) = L(k) − L(N), k ≠ N, in the order of the voxels.
    """
    m = voxels.shape[1]
    if not torch.is_tensor(contrasts):
        contrasts = torch.as_tensor(list(contrasts))
    c = contrasts.to(dtype=voxels.dtype, device=voxels.device)
    c = c.view(1, -1, 1, 1, 1) if c.ndim == 1 else c.view(c.shape[0], c.shape[1], 1, 1, 1)
    logr = (c * voxels.unsqueeze(1)).clamp(-MAX_LOG_RATIO, MAX_LOG_RATIO)
    ratio = torch.exp(logr)                                    # (B, K, 2N, H, W): L(k)/L(N)
    # mean over the 2N+1 instants; the middle one contributes exp(0) = 1
    denom = (ratio.sum(dim=2) + 1.0) / (m + 1)                 # (B, K, H, W)
    middle = blurry.unsqueeze(1) / denom.unsqueeze(2)           # (B, K, C, H, W)
    residuals = middle.unsqueeze(2) * (ratio - 1.0).unsqueeze(3)  # (B, K, 2N, C, H, W)
    return middle, residuals
