"""SCER voxels (Chen & Yu, TMM 2024, Eq. 13) and the signed per-bin event counts they come from.

The exposure ``[t0, t1]`` is cut into 2N equal bins of width Δ = (t1 − t0)/(2N). An event at time
t falls in bin ``floor((t − t0)/Δ)`` clamped to ``[0, 2N − 1]``. With ``b_j`` the signed event
count of bin j, the voxel for latent instant k (t0 + kΔ) is the signed sum between the middle
instant and instant k, sign-flipped before the middle::

    V(k) = −Σ_{j=k}^{N−1} b_j   for k < N        V(k) = +Σ_{j=N}^{k−1} b_j   for k > N

so that V(k) ≈ (log L(k) − log L(N)) / c in both halves. V(N) ≡ 0 is dropped: the tensor has 2N
channels ordered k = 0..N−1, N+1..2N.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError, check_shape
from .events import EventStream, Exposure

__all__ = ["event_bins", "scer_from_bins", "bins_from_scer", "resample_bins", "scer_levels",
           "scer_voxels", "scer_voxels_torch", "voxel_instants"]


def event_bins(events: EventStream, exposure: Exposure, num_bins: int) -> np.ndarray:
    """Signed event counts per bin: (num_bins, H, W) float32.

    Events outside ``[start_us, end_us]`` are ignored; one at ``end_us`` lands in the last bin.
    """
    if num_bins < 1:
        raise InputError(f"num_bins must be ≥ 1, got {num_bins}")
    h, w = events.height, events.width
    ev = events.within(exposure)
    if len(ev) == 0:
        return np.zeros((num_bins, h, w), np.float32)
    # integer arithmetic: exact bin edges whatever the magnitude of t
    b = ((ev.t - exposure.start_us) * num_bins) // exposure.duration_us
    np.clip(b, 0, num_bins - 1, out=b)
    flat = b * (h * w) + ev.y.astype(np.int64) * w + ev.x
    counts = np.bincount(flat, weights=ev.p, minlength=num_bins * h * w)
    return counts.astype(np.float32).reshape(num_bins, h, w)


def scer_from_bins(bins):
    """SCER voxels (2N, H, W) from signed bin counts (2N, H, W); numpy or torch in, same out."""
    check_shape(bins, (None, None, None), "bins")
    m = bins.shape[0]
    if m % 2:
        raise InputError(f"SCER needs an even number of bins (2N), got {m}")
    n = m // 2
    if isinstance(bins, np.ndarray):
        before = -np.flip(np.cumsum(np.flip(bins[:n], 0), 0), 0)  # k = 0..N-1
        after = np.cumsum(bins[n:], 0)  # k = N+1..2N
        return np.concatenate([before, after], 0).astype(np.float32, copy=False)
    import torch

    before = -torch.flip(torch.cumsum(torch.flip(bins[:n], (0,)), 0), (0,))
    after = torch.cumsum(bins[n:], 0)
    return torch.cat([before, after], 0)


def bins_from_scer(voxels: np.ndarray) -> np.ndarray:
    """Invert :func:`scer_from_bins`: SCER (2N, H, W) → signed bin counts.

    With ``V(N) = 0`` put back in place, bin j is ``V(j+1) − V(j)`` (both halves).
    """
    v = np.asarray(voxels, np.float64)
    if v.ndim != 3 or v.shape[0] % 2 or v.shape[0] == 0:
        raise InputError(f"SCER voxels must be (2N, H, W), got {v.shape}")
    n = v.shape[0] // 2
    full = np.concatenate([v[:n], np.zeros((1, *v.shape[1:])), v[n:]], 0)
    return np.diff(full, axis=0)


def resample_bins(bins: np.ndarray, num_bins: int) -> np.ndarray:
    """Signed counts of ``num_bins`` equal bins from those of M equal bins over the same span:
    (num_bins, H, W) float32.

    When ``num_bins`` divides M each new bin is the sum of M / ``num_bins`` whole bins: exact,
    no assumption. Otherwise an old bin that straddles a new bin's edge has its count split in
    proportion to the overlap, i.e. its events are taken as spread evenly over it (the
    assumption :class:`~trmd_cli.edi.EdiBins` makes within a bin); the counts then have
    fractions. The total per pixel is kept either way.
    """
    b = np.asarray(bins)
    if b.ndim != 3 or b.shape[0] == 0:
        raise InputError(f"bins must be (M, H, W) with M ≥ 1, got {b.shape}")
    if num_bins < 1:
        raise InputError(f"num_bins must be ≥ 1, got {num_bins}")
    m = b.shape[0]
    if m % num_bins == 0:
        whole = b.reshape(num_bins, m // num_bins, *b.shape[1:]).sum(axis=1, dtype=np.float64)
        return whole.astype(np.float32)
    # overlaps in units of 1/(M·num_bins): new bin i is [i·M, (i+1)·M), old bin j [j·n, (j+1)·n)
    i = np.arange(num_bins)[:, None]
    j = np.arange(m)[None, :]
    overlap = np.clip(np.minimum((i + 1) * m, (j + 1) * num_bins)
                      - np.maximum(i * m, j * num_bins), 0, None)
    weights = overlap / num_bins  # the share of old bin j that falls in new bin i
    return np.tensordot(weights, b.astype(np.float64), axes=(1, 0)).astype(np.float32)


def scer_voxels(events: EventStream, exposure: Exposure, n: int = 3) -> np.ndarray:
    """SCER voxels (2N, H, W) float32 for one exposure window."""
    if n < 1:
        raise InputError(f"N must be ≥ 1, got {n}", hint="use --n 3 (7 latent frames)")
    return scer_from_bins(event_bins(events, exposure, 2 * n))


def scer_voxels_torch(x, y, t_us, p, exposure: Exposure, n: int, height: int, width: int):
    """Torch twin of :func:`scer_voxels` for event tensors already on a device.

    Args:
        x, y: (E,) integer tensors; t_us: (E,) int64 µs; p: (E,) ±1.
    Returns:
        (2N, H, W) float32 tensor on the same device.
    """
    import torch

    m = 2 * n
    keep = (t_us >= exposure.start_us) & (t_us <= exposure.end_us)
    t, xs, ys, ps = t_us[keep], x[keep].long(), y[keep].long(), p[keep].float()
    b = torch.div((t - exposure.start_us) * m, exposure.duration_us, rounding_mode="floor")
    b = b.clamp_(0, m - 1)
    flat = b * (height * width) + ys * width + xs
    out = torch.zeros(m * height * width, dtype=torch.float32, device=t.device)
    out.index_add_(0, flat, ps)
    return scer_from_bins(out.view(m, height, width))


def scer_levels(events: EventStream, exposure: Exposure, n: int = 3) -> np.ndarray:
    """SCER with sub-bin timing: (2N, H, W) float32, ``Λ(t_k) − Λ(t_N)`` for k ≠ N.

    SCER's counts are a staircase in time: they say how many thresholds a pixel crossed before
    an instant, not how close it was to the next crossing. Λ keeps the timing, following the
    sensor: an event fires when the log intensity reaches the next level, so at each event Λ is
    the signed count so far; between two events it is interpolated linearly in time; before the
    first event it is half-way to it (the middle of where the level can be) and after the last
    it stays at the level reached. On a constant-rate ramp the differences are exact where the
    counts are off by up to a step. Units: events (multiply by c for log intensity).

    Not symmetric in time (nor is the sensor: the reference resets at each event), so the
    training augmentation does not time-reverse samples that carry levels.

    Instants and bin edges use the same integer arithmetic as :func:`scer_voxels`: an event
    exactly at an instant counts as after it.
    """
    if n < 1:
        raise InputError(f"N must be ≥ 1, got {n}", hint="use --n 3 (7 latent frames)")
    h, w = events.height, events.width
    m = 2 * n
    out = np.zeros((m, h * w), np.float32)
    ev = events.within(exposure)
    if len(ev) == 0:
        return out.reshape(m, h, w)
    # times scaled by 2N, instants by the duration: instant k is exactly k·T in these units
    dur = int(exposure.duration_us)
    rel = (ev.t - exposure.start_us) * m
    pix = ev.y.astype(np.int64) * w + ev.x
    e = len(rel)
    # per pixel, in time order: the event index breaks ties (a unique key; faster than a
    # stable sort)
    order = np.argsort(pix * e + np.arange(e))
    rel, pix = rel[order], pix[order]
    p = ev.p[order].astype(np.float64)
    level = np.cumsum(p)
    count_all = np.bincount(pix, minlength=h * w)
    uniq = np.flatnonzero(count_all)
    count = count_all[uniq]
    end = np.cumsum(count)
    start = end - count
    base = np.where(start > 0, level[start - 1], 0.0)  # the running sum before each pixel
    # events of each pixel before each instant: an event exactly at instant k counts as after
    # it (bin k), as in scer_voxels
    slot = np.repeat(np.arange(len(uniq), dtype=np.int64), count)
    per_bin = np.bincount(slot * (m + 1) + np.minimum(rel // dur, m), minlength=len(uniq) * (m + 1))
    before = np.cumsum(per_bin.reshape(-1, m + 1), axis=1)
    lv = np.empty((m + 1, len(uniq)))
    for k in range(m + 1):
        g = k * dur
        j = start + (before[:, k - 1] if k else 0)  # the pixel's first event at or after g
        prev, nxt = j > start, j < end
        jp, jn = np.maximum(j - 1, 0), np.minimum(j, e - 1)
        sp = level[jp] - base  # the level the previous event reached
        gap = np.maximum(rel[jn] - rel[jp], 1).astype(np.float64)
        frac = np.clip((g - rel[jp]) / gap, 0.0, 1.0)
        lv[k] = np.where(prev & nxt, sp + frac * p[jn], np.where(nxt, 0.5 * p[jn], sp))
    rows = [k for k in range(m + 1) if k != n]
    out[:, uniq] = (lv[rows] - lv[n]).astype(np.float32)
    return out.reshape(m, h, w)


def voxel_instants(n: int) -> list[int]:
    """Latent-frame index k of each voxel channel: [0..N−1, N+1..2N]."""
    return [k for k in range(2 * n + 1) if k != n]
