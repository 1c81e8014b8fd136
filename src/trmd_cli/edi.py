"""EDI: the Event-based Double Integral (Pan et al., "Bringing a Blurry Frame Alive at High
Frame-Rate with an Event Camera", CVPR 2019).

Model. A pixel's latent intensity changes only at its events: ``L(t) = L(f)·exp(c·E(f, t))``
with ``E(f, t)`` the signed event count between a reference time ``f`` and ``t`` and ``c`` the
contrast threshold. The blurry frame is the mean latent intensity over the exposure
``[t0, t1]`` (length T)::

    B = (1/T) ∫ L(t) dt = L(f) · (1/T) ∫ exp(c·E(f, t)) dt

``E`` is piecewise constant between a pixel's events, so the integral is *exact*: a sum over the
pixel's inter-event intervals of ``duration · exp(c · level)``. Writing ``S(t)`` for the signed
count since ``t0`` the reference cancels and every latent frame is::

    L(t) = B · exp(c·S(t)) / J,        J = (1/T) Σ_intervals Δt_i · exp(c·S_i)

This module computes that for all pixels at once (one sort by pixel, one ``bincount`` per ``c``:
O(events + pixels)). A colour blurry frame with mono events is handled per channel: the ratio
``exp(c·S)/J`` is the same for the three channels (events carry no colour).

:class:`EdiEvents` holds the per-pixel interval table of one window so that the contrast search
in :mod:`trmd_cli.threshold` re-evaluates ``J`` cheaply for many ``c``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError, ShapeError
from .events import EventStream, Exposure

__all__ = [
    "EdiEvents",
    "EdiBins",
    "edi_latent",
    "edi_from_bins",
    "hot_pixel_mask",
    "check_blurry",
    "exp_levels",
    "signed_counts",
    "propagate",
]


def check_blurry(blurry: np.ndarray, width: int, height: int, path=None) -> np.ndarray:
    """Validate a blurry frame against the sensor size; return it as float32.

    Raises:
        InputError: size differs from the sensor, or values are not finite.
    """
    b = np.asarray(blurry)
    if b.ndim not in (2, 3) or (b.ndim == 3 and b.shape[2] != 3):
        raise ShapeError(f"blurry frame has shape {b.shape}, expected (H, W) or (H, W, 3)")
    if b.shape[:2] != (height, width):
        raise InputError(f"image is {b.shape[1]}x{b.shape[0]} but the events' sensor is "
                         f"{width}x{height}", path=path,
                         hint="pass the frame that belongs to these events, or `sensor=(W, H)`")
    b = b.astype(np.float32, copy=False)
    if not np.isfinite(b).all():
        raise InputError("blurry frame has NaN or infinite values", path=path)
    return b


def hot_pixel_mask(events: EventStream, exposure: Exposure | None = None,
                   factor: float = 8.0, min_count: int = 16) -> np.ndarray:
    """Pixels firing far more than the rest: (H, W) bool, True = hot.

    A pixel is hot when its event count in the window exceeds both ``min_count`` and
    ``median + factor · 1.4826 · MAD`` of the counts of the active pixels (robust z-score), and
    when its *net* signed count is also extreme (a moving edge produces many events too, but
    they go up and back down; a hot pixel drifts one way). EDI multiplies by
    ``exp(c · net count)``, so one hot pixel otherwise becomes a white or black dot.
    """
    ev = events if exposure is None else events.within(exposure)
    h, w = events.height, events.width
    flat = ev.y.astype(np.int64) * w + ev.x
    count = np.bincount(flat, minlength=h * w)
    net = np.bincount(flat, weights=ev.p, minlength=h * w)
    active = count[count > 0]
    if active.size < 16:
        return np.zeros((h, w), bool)
    med = np.median(active)
    mad = 1.4826 * np.median(np.abs(active - med)) + 1.0
    anet = np.abs(net[count > 0])
    nmed = np.median(anet)
    nmad = 1.4826 * np.median(np.abs(anet - nmed)) + 1.0
    hot = ((count > max(min_count, med + factor * mad))
           & (np.abs(net) > max(min_count / 2, nmed + factor * nmad)))
    return hot.reshape(h, w)


@dataclass(frozen=True, eq=False)
class EdiEvents:
    """Per-pixel inter-event intervals of one exposure window, ready for any ``c``.

    Attributes:
        pix: (M,) int64 flat pixel index (y·W + x) of the interval starting at each event.
        time: (M,) float64 event time as a fraction of the window (0 = start, 1 = end).
        step: (M,) float64 event polarity ±1.
        level: (M,) int64 signed count S of that pixel just after the event.
        dur: (M,) float64 interval length as a fraction of T (to the next event of the same
            pixel, or to the window's end).
        lead: (H·W,) float64 fraction of T before a pixel's first event (1 for silent pixels).
        width, height: sensor size.
        exposure: the window (µs).
        count: number of events used.
    """

    pix: np.ndarray
    time: np.ndarray
    step: np.ndarray
    level: np.ndarray
    dur: np.ndarray
    lead: np.ndarray
    width: int
    height: int
    exposure: Exposure
    count: int

    @classmethod
    def build(cls, events: EventStream, exposure: Exposure,
              hot_mask: np.ndarray | None = None) -> EdiEvents:
        """Sort the window's events by pixel (stable: time order kept within a pixel).

        ``hot_mask`` (H, W) bool drops those pixels' events (their latent stays ``B``).
        """
        ev = events.within(exposure)
        h, w = events.height, events.width
        n_pix = h * w
        flat = ev.y.astype(np.int64) * w + ev.x.astype(np.int64)
        t = ev.t
        p = ev.p
        if hot_mask is not None and hot_mask.any():
            keep = ~hot_mask.reshape(-1)[flat]
            flat, t, p = flat[keep], t[keep], p[keep]
        T = float(exposure.duration_us)
        lead = np.ones(n_pix, np.float64)
        if len(flat) == 0:
            z = np.zeros(0)
            return cls(np.zeros(0, np.int64), z, z, np.zeros(0, np.int64), z, lead, w, h,
                       exposure, 0)
        order = np.argsort(flat, kind="stable")
        pix = flat[order]
        ts = (t[order] - exposure.start_us).astype(np.float64) / T
        ps = p[order].astype(np.int64)
        new = np.empty(len(pix), bool)
        new[0] = True
        np.not_equal(pix[1:], pix[:-1], out=new[1:])
        starts = np.flatnonzero(new)
        group = np.cumsum(new) - 1
        cs = np.cumsum(ps)
        level = cs - (cs[starts] - ps[starts])[group]
        nxt = np.empty_like(ts)
        nxt[:-1] = ts[1:]
        nxt[-1] = 1.0
        last = np.empty(len(pix), bool)
        last[:-1] = new[1:]
        last[-1] = True
        nxt[last] = 1.0
        dur = np.clip(nxt - ts, 0.0, None)
        lead[pix[starts]] = np.clip(ts[starts], 0.0, 1.0)
        return cls(pix, ts, ps.astype(np.float64), level, dur, lead, w, h, exposure, len(pix))

    def integral(self, contrast: float) -> np.ndarray:
        """J = (1/T) ∫ exp(c·S(t)) dt per pixel: (H, W) float64, exact."""
        acc = np.bincount(self.pix, weights=self.dur * exp_levels(self.level, contrast),
                          minlength=self.width * self.height)
        return (acc + self.lead).reshape(self.height, self.width)

    def levels_at(self, fractions: np.ndarray) -> np.ndarray:
        """S at instants given as fractions of the window (0 = start, 1 = end): (K, H, W).

        Only events inside the window count; instants outside ``[0, 1]`` are clamped.
        """
        fr = np.clip(np.asarray(fractions, np.float64).reshape(-1), 0.0, 1.0)
        k = len(fr)
        order = np.argsort(fr, kind="stable")
        sorted_fr = fr[order]
        n_pix = self.width * self.height
        if self.count == 0:
            return np.zeros((k, self.height, self.width), np.float64)
        # the event's own time: an interval starts at the event, the step happens at it
        slot = np.searchsorted(sorted_fr, self.time, side="left")  # first instant at or after
        keep = slot < k
        counts = np.bincount(slot[keep] * n_pix + self.pix[keep], weights=self.step[keep],
                             minlength=k * n_pix).reshape(k, n_pix)
        np.cumsum(counts, axis=0, out=counts)
        out = np.empty_like(counts)
        out[order] = counts
        return out.reshape(k, self.height, self.width)

    def latent(self, blurry: np.ndarray, fractions: np.ndarray, contrast: float) -> np.ndarray:
        """``L = B · exp(c·S(t)) / J`` at the given window fractions: (K, H, W[, 3]) float32."""
        ratio = self.ratio(fractions, contrast)
        if blurry.ndim == 3:
            return (ratio[..., None] * blurry[None]).astype(np.float32)
        return (ratio * blurry[None]).astype(np.float32)

    def ratio(self, fractions: np.ndarray, contrast: float) -> np.ndarray:
        """``exp(c·S(t)) / J``: (K, H, W) float32, the factor applied to the blurry frame."""
        j = self.integral(contrast)
        s = self.levels_at(fractions)
        return (exp_levels(s, contrast) / j[None]).astype(np.float32)


def exp_levels(level: np.ndarray, contrast: float) -> np.ndarray:
    """``exp(c · level)`` for whole-number levels, by table look-up (levels span a small range,
    so this replaces millions of ``exp`` calls by a gather)."""
    if level.size == 0:
        return np.ones(level.shape, np.float64)
    lo, hi = int(level.min()), int(level.max())
    if hi - lo > 1 << 16:
        return np.exp(contrast * level.astype(np.float64))
    table = np.exp(contrast * np.arange(lo, hi + 1, dtype=np.float64))
    idx = level if level.dtype.kind in "iu" else np.rint(level).astype(np.int64)
    return table[idx - lo] if lo else table[idx]


def signed_counts(events: EventStream, ref_us: float, targets_us,
                  hot_mask: np.ndarray | None = None) -> np.ndarray:
    """``S(t) − S(ref)`` per pixel for each target t: (K, H, W) float32.

    ``S(t)`` counts polarities of events with time ≤ t, so a later target adds the events in
    ``(ref, t]`` and an earlier one subtracts those in ``(t, ref]``.
    """
    targets = np.asarray(targets_us, np.float64).reshape(-1)
    h, w = events.height, events.width
    k = len(targets)
    if k == 0:
        return np.zeros((0, h, w), np.float32)
    q = np.concatenate([targets, [float(ref_us)]])
    order = np.argsort(q, kind="stable")
    qs = q[order]
    i0 = int(np.searchsorted(events.t, qs[0], side="right"))
    i1 = int(np.searchsorted(events.t, qs[-1], side="right"))
    t = events.t[i0:i1]
    flat = events.y[i0:i1].astype(np.int64) * w + events.x[i0:i1]
    p = events.p[i0:i1].astype(np.float64)
    if hot_mask is not None and hot_mask.any() and len(flat):
        keep = ~hot_mask.reshape(-1)[flat]
        t, flat, p = t[keep], flat[keep], p[keep]
    slot = np.searchsorted(qs, t, side="left")  # first query point at or after the event
    cum = np.bincount(slot * (h * w) + flat, weights=p, minlength=(k + 1) * h * w)
    cum = np.cumsum(cum.reshape(k + 1, h * w), axis=0)
    at = np.empty_like(cum)
    at[order] = cum
    return (at[:k] - at[k][None]).reshape(k, h, w).astype(np.float32)


def propagate(frame: np.ndarray, events: EventStream, ref_us: float, targets_us,
              contrast: float, hot_mask: np.ndarray | None = None) -> np.ndarray:
    """Frames at other instants from one frame by event integration (EDI's forward model).

    ``L(t) = L(ref) · exp(c · (S(t) − S(ref)))``, per colour channel alike.

    Args:
        frame: (H, W) or (H, W, 3) float32, the latent frame at ``ref_us``.
        events: a stream covering ``ref_us`` … each target.
        ref_us: the frame's time, µs.
        targets_us: (K,) times, µs, before or after ``ref_us``.
        contrast: c > 0.
    Returns:
        (K, H, W[, 3]) float32.
    """
    _check_contrast(contrast)
    ratio = np.exp(np.float32(contrast) * signed_counts(events, ref_us, targets_us, hot_mask))
    if frame.ndim == 3:
        return (ratio[..., None] * frame[None]).astype(np.float32)
    return (ratio * frame[None]).astype(np.float32)


def edi_latent(blurry: np.ndarray, events: EventStream, exposure: Exposure,
               instants_us, contrast: float, *, hot_mask: np.ndarray | None = None
               ) -> np.ndarray:
    """Latent sharp frames at given instants by EDI.

    Args:
        blurry: (H, W) or (H, W, 3) float32 in [0, 1], linear intensity, the mean over the
            exposure.
        events: the stream (only events in ``[start_us, end_us]`` are used).
        exposure: the blurry frame's exposure window on the events' clock (µs).
        instants_us: (K,) times in µs inside the window (clamped to it).
        contrast: contrast threshold c (log-intensity step per event), > 0.
        hot_mask: optional (H, W) bool of pixels whose events are ignored.

    Returns:
        (K, H, W) or (K, H, W, 3) float32; values may exceed 1 (the caller clips when writing).

    Raises:
        InputError: image size differs from the sensor, c is not positive.
    """
    b = check_blurry(blurry, events.width, events.height)
    _check_contrast(contrast)
    prep = EdiEvents.build(events, exposure, hot_mask)
    fr = (np.asarray(instants_us, np.float64) - exposure.start_us) / exposure.duration_us
    return prep.latent(b, fr, contrast)


def _check_contrast(contrast: float) -> None:
    if not (np.isfinite(contrast) and contrast > 0):
        raise InputError(f"contrast threshold must be a positive number, got {contrast}",
                         hint="use `contrast='auto'` or a value like 0.2")


@dataclass(frozen=True, eq=False)
class EdiBins:
    """Binned events of one span, ready for any ``c`` (the binned twin of :class:`EdiEvents`).

    The bins cut a span into M equal parts; within a bin the event times are unknown, so the
    log intensity is taken to change *linearly* across the bin (its count spread evenly), which
    gives the exact integral ``∫₀¹ exp(c(S + b·u)) du = exp(cS)·(exp(cb) − 1)/(cb)``.

    Attributes:
        bins: (M, H, W) float64 signed counts.
        edges: (M+1, H, W) float64 signed count S at the bin edges (0 at the span's start).
        exposure: (f0, f1) part of the span the blurry frame integrates, fractions.
    """

    bins: np.ndarray
    edges: np.ndarray
    exposure: tuple[float, float]

    @classmethod
    def build(cls, bins: np.ndarray, exposure: tuple[float, float] = (0.0, 1.0)) -> EdiBins:
        bins = np.asarray(bins)
        if bins.ndim != 3:
            raise ShapeError(f"bins have shape {bins.shape}, expected (M, H, W)")
        if not np.isfinite(bins).all():
            raise InputError("bins hold NaN or infinite values")
        f0, f1 = (float(v) for v in exposure)
        if not 0.0 <= f0 < f1 <= 1.0:
            raise InputError(f"exposure fractions {exposure} must satisfy 0 ≤ f0 < f1 ≤ 1")
        b = bins.astype(np.float64)
        edges = np.zeros((b.shape[0] + 1, *b.shape[1:]))
        np.cumsum(b, axis=0, out=edges[1:])
        return cls(b, edges, (f0, f1))

    @property
    def width(self) -> int:
        return self.bins.shape[2]

    @property
    def height(self) -> int:
        return self.bins.shape[1]

    def levels_at(self, fractions) -> np.ndarray:
        """S at instants (fractions of the span, clamped to [0, 1]): (K, H, W) float64."""
        m = self.bins.shape[0]
        out = []
        for fr in np.ravel(fractions):
            x = min(max(float(fr), 0.0), 1.0) * m
            j = min(int(np.floor(x)), m - 1)
            out.append(self.edges[j] + (x - j) * self.bins[j])
        return np.stack(out) if out else np.zeros((0, self.height, self.width))

    def integral(self, contrast: float) -> np.ndarray:
        """(1/T_exp) ∫ exp(c·S) over the exposure part of the span: (H, W) float64."""
        m = self.bins.shape[0]
        lo, hi = self.exposure[0] * m, self.exposure[1] * m
        acc = np.zeros(self.bins.shape[1:])
        for j in range(int(np.floor(lo)), min(int(np.ceil(hi)), m)):
            a, z = max(lo, j), min(hi, j + 1)
            if z > a:
                s_a = self.edges[j] + (a - j) * self.bins[j]
                acc += (z - a) * _exp_mean(contrast, s_a, self.bins[j] * (z - a))
        return acc / (hi - lo)

    def ratio(self, fractions, contrast: float) -> np.ndarray:
        """``exp(c·S(t)) / J``: (K, H, W) float32."""
        j = self.integral(contrast)
        return (np.exp(contrast * self.levels_at(fractions)) / j[None]).astype(np.float32)

    def latent(self, blurry: np.ndarray, fractions, contrast: float) -> np.ndarray:
        ratio = self.ratio(fractions, contrast)
        if blurry.ndim == 3:
            return (ratio[..., None] * blurry[None]).astype(np.float32)
        return (ratio * blurry[None]).astype(np.float32)


def edi_from_bins(blurry: np.ndarray, bins: np.ndarray, instants, contrast: float, *,
                  exposure: tuple[float, float] = (0.0, 1.0)) -> np.ndarray:
    """EDI from per-bin signed event counts, for data that ships only binned events.

    Within a bin the log intensity is taken to change linearly (see :class:`EdiBins`).

    Args:
        blurry: (H, W) or (H, W, 3) float32, the mean intensity over ``exposure``.
        bins: (M, H, W) signed event counts of M equal consecutive bins.
        instants: (K,) instants as fractions of the bins' span (0 = start of bin 0, 1 = end of
            bin M−1).
        contrast: contrast threshold c > 0.
        exposure: (f0, f1) part of the span the blurry frame integrates, as fractions (the
            bins may reach into the gaps around the exposure).

    Returns:
        (K, H, W[, 3]) float32.
    """
    model = EdiBins.build(bins, exposure)
    b = check_blurry(blurry, model.width, model.height)
    _check_contrast(contrast)
    return model.latent(b, instants, contrast)


def _exp_mean(c: float, s0: np.ndarray, ds: np.ndarray) -> np.ndarray:
    """Mean of exp(c·s) for s running linearly from s0 to s0 + ds."""
    x = c * ds
    small = np.abs(x) < 1e-6
    safe = np.where(small, 1.0, x)
    factor = np.where(small, 1.0 + x / 2, np.expm1(safe) / safe)
    return np.exp(c * s0) * factor
