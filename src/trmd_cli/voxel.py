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

from .edi import PixelEvents, cumsum_rows
from .errors import InputError, check_shape
from .events import EventStream, Exposure, check_n

__all__ = ["event_bins", "scer_from_bins", "bins_from_scer", "resample_bins", "spread_bins",
           "scer_levels", "scer_voxels", "scer_voxels_torch", "voxel_instants"]


def event_bins(events: EventStream, exposure: Exposure, num_bins: int, *,
               window: PixelEvents | None = None) -> np.ndarray:
    """Signed event counts per bin: (num_bins, H, W) float32.

    Events outside ``[start_us, end_us]`` are ignored; one at ``end_us`` lands in the last bin.
    ``window``: the events of ``exposure`` already sorted per pixel
    (:class:`~trmd_cli.edi.PixelEvents`); the counts are the same, made on the fired pixels only.
    """
    num_bins = check_n(num_bins, "num_bins", hint=None)
    h, w = events.height, events.width
    if window is not None:
        _check_window(window, exposure)
        out = np.zeros((num_bins, h * w), np.float32)
        if len(window):
            b = (window.t_rel * num_bins) // exposure.duration_us
            np.clip(b, 0, num_bins - 1, out=b)
            u = len(window.starts)
            counts = np.bincount(b * u + window.group, weights=window.p,
                                 minlength=num_bins * u)
            out[:, window.pixels] = counts.reshape(num_bins, u)
        return out.reshape(num_bins, h, w)
    ev = events.within(exposure)
    if len(ev) == 0:
        return np.zeros((num_bins, h, w), np.float32)
    # integer arithmetic: exact bin edges whatever the magnitude of t
    b = ((ev.t - exposure.start_us) * num_bins) // exposure.duration_us
    np.clip(b, 0, num_bins - 1, out=b)
    flat = b * (h * w) + ev.y.astype(np.int64) * w + ev.x
    counts = np.bincount(flat, weights=ev.p, minlength=num_bins * h * w)
    return counts.astype(np.float32).reshape(num_bins, h, w)


def _check_window(window: PixelEvents, exposure: Exposure) -> None:
    if window.exposure != exposure:
        raise InputError(f"the sorted events are of the window {window.exposure}, not of "
                         f"{exposure}", hint="build the PixelEvents of this exposure")


def scer_from_bins(bins):
    """SCER voxels (2N, H, W) from signed bin counts (2N, H, W); numpy or torch in, same out."""
    check_shape(bins, (None, None, None), "bins")
    m = bins.shape[0]
    if m % 2:
        raise InputError(f"SCER needs an even number of bins (2N), got {m}")
    n = m // 2
    if isinstance(bins, np.ndarray):
        # running sums one plane at a time (numpy's cumsum along the first axis is several times
        # slower; the same additions in the same order, negated: -(x + y) = (-x) - y exactly)
        # in the type numpy's cumsum would sum in (integers widen), signed: the sums before
        # the middle are negated, which an unsigned type would wrap around
        total = np.cumsum(bins[:0, :1, :1]).dtype
        bins = bins.astype(np.int64 if total.kind == "u" else total, copy=False)
        out = np.empty(bins.shape, bins.dtype)  # C order whatever the input's, as before
        if m == 0:
            return out.astype(np.float32)
        np.negative(bins[n - 1], out=out[n - 1])  # k = 0..N-1: minus the bins up to the middle
        for k in range(n - 2, -1, -1):
            np.subtract(out[k + 1], bins[k], out=out[k])
        out[n] = bins[n]  # k = N+1..2N: the bins from the middle on
        for k in range(n + 1, m):
            np.add(out[k - 1], bins[k], out=out[k])
        return out.astype(np.float32, copy=False)
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


def spread_bins(bins: np.ndarray, bin_us: int = 10_000) -> tuple[EventStream, Exposure]:
    """Events standing in for signed bin counts (M, H, W): a count k of a pixel's bin becomes
    |k| events of its sign spread evenly over the bin, on a nominal clock of ``bin_us`` µs per
    bin starting at 0 — what EDI on binned data assumes of them.

    For what needs event times (contrast maximisation, the motion-aware deconvolution) on
    data that has none; the times are a model, never written out as the recording's. The
    bins come back exactly: ``event_bins(events, exposure, M)`` equals ``bins``.
    Returns:
        the events (width, height from the bins) and their exposure ``[0, M · bin_us]``.
    """
    check_shape(bins, (None, None, None), "bins")
    counts = np.asarray(bins)
    if not np.all(np.isfinite(counts)) or np.any(counts != np.round(counts)):
        raise InputError("bin counts must be whole numbers", hint="give signed event counts")
    m, h, w = counts.shape
    ib = np.rint(counts).astype(np.int64)
    b, y, x = np.nonzero(ib)
    k = np.abs(ib[b, y, x])
    reps = np.repeat(np.arange(len(k)), k)
    # j-th of k events of a bin at (j + ½)/k of it: evenly spread, strictly inside
    j = np.arange(len(reps)) - np.repeat(np.cumsum(k) - k, k)
    t = b[reps] * bin_us + ((2 * j + 1) * bin_us) // (2 * k[reps])
    order = np.argsort(t, kind="stable")
    events = EventStream(x[reps][order].astype(np.uint16), y[reps][order].astype(np.uint16),
                         t[order].astype(np.int64),
                         np.sign(ib[b, y, x])[reps][order].astype(np.int8), w, h)
    return events, Exposure(0, m * bin_us)


def scer_voxels(events: EventStream, exposure: Exposure, n: int = 3, *,
                window: PixelEvents | None = None) -> np.ndarray:
    """SCER voxels (2N, H, W) float32 for one exposure window (``window``: its events already
    sorted per pixel, see :func:`event_bins`)."""
    return scer_from_bins(event_bins(events, exposure, 2 * check_n(n), window=window))


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


def scer_levels(events: EventStream, exposure: Exposure, n: int = 3, *,
                window: PixelEvents | None = None) -> np.ndarray:
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
    exactly at an instant counts as after it. ``window``: the events of ``exposure`` already
    sorted per pixel (:class:`~trmd_cli.edi.PixelEvents`), to skip the sort.
    """
    if n < 1:
        raise InputError(f"N must be ≥ 1, got {n}", hint="use --n 3 (7 latent frames)")
    h, w = events.height, events.width
    m = 2 * n
    out = np.zeros((m, h * w), np.float32)
    if window is None:
        window = PixelEvents.build(events, exposure)
    else:
        _check_window(window, exposure)
    e = len(window)
    if e == 0:
        return out.reshape(m, h, w)
    # times scaled by 2N, instants by the duration: instant k is exactly k·T in these units
    dur = int(exposure.duration_us)
    rel = window.t_rel * m
    p = window.p.astype(np.float64)
    level = np.cumsum(p)
    uniq, start, group = window.pixels, window.starts, window.group
    u = len(uniq)
    end = np.append(start[1:], e)
    base = np.where(start > 0, level[start - 1], 0.0)  # the running sum before each pixel
    # events of each pixel before each instant: an event exactly at instant k counts as after
    # it (bin k), as in scer_voxels
    per_bin = np.bincount(np.minimum(rel // dur, m) * u + group, minlength=(m + 1) * u)
    before = cumsum_rows(per_bin.reshape(m + 1, u))
    # row k: each pixel's first event at or after instant k
    j = np.empty((m + 1, u), np.int64)
    j[0] = start
    np.add(start, before[:m], out=j[1:])
    prev, nxt = j > start, j < end
    jp = np.maximum(j - 1, 0)
    jn = np.minimum(j, e - 1, out=j)
    sp = level[jp] - base  # the level the previous event reached
    rel_p = rel[jp]
    gap = np.maximum(rel[jn] - rel_p, 1).astype(np.float64)
    g = (np.arange(m + 1, dtype=np.int64) * dur)[:, None]
    lv = np.subtract(g, rel_p, out=rel_p) / gap
    np.clip(lv, 0.0, 1.0, out=lv)
    pn = p[jn]
    # between two events: interpolated; before the first: half-way to it; after the last: the
    # level reached
    lv *= pn
    lv += sp
    np.multiply(pn, 0.5, out=pn)
    np.copyto(lv, pn, where=nxt & ~prev)
    np.copyto(lv, sp, where=~nxt)
    rows = [k for k in range(m + 1) if k != n]
    out[:, uniq] = lv[rows] - lv[n]
    return out.reshape(m, h, w)


def voxel_instants(n: int) -> list[int]:
    """Latent-frame index k of each voxel channel: [0..N−1, N+1..2N]."""
    return [k for k in range(2 * n + 1) if k != n]
