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
O(events + pixels)); the per-pixel work touches only the pixels that fired. A colour blurry
frame with mono events is handled per channel: the ratio ``exp(c·S)/J`` is the same for the
three channels (events carry no colour).

:class:`EdiEvents` holds the per-pixel interval table of one window so that the contrast search
in :mod:`trmd_cli.threshold` re-evaluates ``J`` cheaply for many ``c``. It is built from a
:class:`PixelEvents`, the window's events sorted per pixel once, which the voxels and their
timing levels (:mod:`trmd_cli.voxel`) and the hot-pixel mask reuse.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .errors import InputError, ShapeError
from .events import EventStream, Exposure

__all__ = [
    "PixelEvents",
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
                   factor: float = 8.0, min_count: int = 16, *,
                   window: PixelEvents | None = None) -> np.ndarray:
    """Pixels firing far more than the rest: (H, W) bool, True = hot.

    A pixel is hot when its event count in the window exceeds both ``min_count`` and
    ``median + factor · 1.4826 · MAD`` of the counts of the active pixels (robust z-score), and
    when its *net* signed count is also extreme (a moving edge produces many events too, but
    they go up and back down; a hot pixel drifts one way). EDI multiplies by
    ``exp(c · net count)``, so one hot pixel otherwise becomes a white or black dot.

    ``window``: the events of ``exposure`` already sorted per pixel (:class:`PixelEvents`),
    used instead of selecting them again (the counts do not depend on the order).
    """
    h, w = events.height, events.width
    if window is not None:
        # sorted per pixel: each fired pixel's events are one run (counts and sums of runs,
        # over the pixels that fired only)
        _check_window(window, exposure)
        fired, starts = window.pixels, window.starts
        active = np.diff(starts, append=len(window))
        anet = np.abs(np.add.reduceat(window.p, starts, dtype=np.int64)) if len(starts) \
            else np.zeros(0, np.int64)
    else:
        ev = events if exposure is None else events.within(exposure)
        flat = ev.y.astype(np.int64) * w + ev.x
        count = np.bincount(flat, minlength=h * w)
        net = np.bincount(flat, weights=ev.p, minlength=h * w)
        fired = np.flatnonzero(count)
        active, anet = count[fired], np.abs(net[fired]).astype(np.int64)  # whole numbers
    if active.size < 16:
        return np.zeros((h, w), bool)
    med, mad = _median_and_deviation(active)
    nmed, nmad = _median_and_deviation(anet)
    mad, nmad = 1.4826 * mad + 1.0, 1.4826 * nmad + 1.0
    # a pixel that never fired has count 0 and net 0, below both bounds (each ≥ 1)
    hot = np.zeros(h * w, bool)
    hot[fired[(active > max(min_count, med + factor * mad))
              & (anet > max(min_count / 2, nmed + factor * nmad))]] = True
    return hot.reshape(h, w)


def _median_and_deviation(counts: np.ndarray) -> tuple[float, float]:
    """``np.median(counts)`` and the median absolute deviation from it, exactly, for counts
    (whole numbers ≥ 0) spanning a small range: by a histogram instead of two partitions
    (several times faster for a window's tens of thousands of pixels)."""
    top = int(counts.max())
    if top > 4 * len(counts) + (1 << 16):  # a histogram wider than the data: partition
        med = float(np.median(counts))
        return med, float(np.median(np.abs(counts - med)))
    hist = np.bincount(counts, minlength=top + 1)
    med2 = _twice_median(hist, len(counts))
    # deviations in halves: |2·count − 2·median| are whole numbers, their histogram is the
    # counts' histogram folded at 2·median
    twice = np.abs(2 * np.arange(top + 1) - med2)
    dev = np.bincount(twice, weights=hist, minlength=int(twice.max()) + 1).astype(np.int64)
    return med2 / 2, _twice_median(dev, len(counts)) / 4


def _twice_median(hist: np.ndarray, n: int) -> int:
    """Twice the median of ``n`` whole numbers given by their histogram (value → how many):
    the sum of the two middle values (the middle value twice for odd ``n``)."""
    cum = np.cumsum(hist)
    low = int(np.searchsorted(cum, (n - 1) // 2, side="right"))
    high = int(np.searchsorted(cum, n // 2, side="right"))
    return low + high


@dataclass(frozen=True, eq=False)
class PixelEvents:
    """The events of one exposure window sorted by pixel, time order kept within each pixel.

    The one per-pixel sort of a window: :class:`EdiEvents`, the voxels' timing levels
    (:func:`trmd_cli.voxel.scer_levels`), the voxels and the hot-pixel mask all start from it.

    Attributes:
        pix: (E,) int64 flat pixel index y·W + x, non-decreasing.
        t_rel: (E,) int64 event time minus the window's start, µs (0 … duration).
        p: (E,) int8 polarity ±1.
        width, height: sensor size.
        exposure: the window (µs); only events with ``start_us ≤ t ≤ end_us`` are held.
    """

    pix: np.ndarray
    t_rel: np.ndarray
    p: np.ndarray
    width: int
    height: int
    exposure: Exposure

    @classmethod
    def build(cls, events: EventStream, exposure: Exposure) -> PixelEvents:
        ev = events.within(exposure)
        w = events.width
        flat = ev.y.astype(np.int64) * w + ev.x.astype(np.int64)
        order = _pixel_order(flat, events.width * events.height)
        return cls(flat[order], ev.t[order] - exposure.start_us, ev.p[order], w, events.height,
                   exposure)

    def __len__(self) -> int:
        return len(self.pix)

    @cached_property
    def starts(self) -> np.ndarray:
        """(U,) int64 index of each active pixel's first event (U pixels fired)."""
        if len(self.pix) == 0:
            return np.zeros(0, np.int64)
        return np.flatnonzero(np.concatenate([[True], self.pix[1:] != self.pix[:-1]]))

    @property
    def pixels(self) -> np.ndarray:
        """(U,) int64 flat index of the pixels that fired, increasing."""
        return self.pix[self.starts]

    @cached_property
    def group(self) -> np.ndarray:
        """(E,) int64 which active pixel (0 … U−1) each event belongs to."""
        return np.repeat(np.arange(len(self.starts), dtype=np.int64),
                         np.diff(np.append(self.starts, len(self.pix))))

    def without(self, hot_mask: np.ndarray | None) -> PixelEvents:
        """The same window without the events of the pixels ``hot_mask`` (H, W) marks."""
        check_mask(hot_mask, self.width, self.height)
        if hot_mask is None or not hot_mask.any() or len(self.pix) == 0:
            return self
        keep = ~hot_mask.reshape(-1)[self.pix]
        return PixelEvents(self.pix[keep], self.t_rel[keep], self.p[keep], self.width,
                           self.height, self.exposure)


def finite_instants(instants) -> np.ndarray:
    """``instants`` as a flat float64 array, refused where one is NaN or infinite (clamping
    would put it at an end of the window, silently)."""
    out = np.asarray(instants, np.float64).reshape(-1)
    if not np.isfinite(out).all():
        bad = out[~np.isfinite(out)][0]
        raise InputError(f"an instant is {bad}: the instants must be finite numbers",
                         hint="give times inside the exposure (µs) or fractions of it")
    return out


def check_mask(mask: np.ndarray | None, width: int, height: int, what: str = "hot_mask"
               ) -> None:
    """Refuse a pixel mask that is not (H, W) bool for a ``width`` × ``height`` sensor: a
    flattened mask of another shape would mark other pixels."""
    if mask is None:
        return
    mask = np.asarray(mask)
    if mask.shape != (height, width) or mask.dtype != bool:
        raise InputError(f"`{what}` is {mask.dtype} of shape {mask.shape}, expected bool of "
                         f"shape ({height}, {width}) for the {width}x{height} sensor",
                         hint="one True per pixel whose events are to be ignored")


def _check_window(window: PixelEvents, exposure: Exposure | None) -> None:
    if exposure is not None and window.exposure != exposure:
        raise InputError(f"the sorted events are of the window {window.exposure}, not of "
                         f"{exposure}", hint="build the PixelEvents of this exposure")


def _pixel_order(flat: np.ndarray, n_pix: int) -> np.ndarray:
    """The stable order of ``flat``: by pixel, ties in their given (time) order.

    Up to 2**32 pixels: a least-significant-digit radix sort in 16-bit digits (numpy's stable
    argsort of 16-bit keys is a radix sort: one pass per digit, a second only for sensors of
    more than 65,536 pixels), twice as fast as sorting one packed key. Else the packed key
    (pixel above, index below), several times faster than a stable argsort on int64.
    """
    e = len(flat)
    if 0 < e and n_pix <= 1 << 32:
        order = np.argsort((flat & 0xFFFF).astype(np.uint16), kind="stable")
        if n_pix <= 1 << 16:
            return order
        high = (flat >> 16).astype(np.uint16)[order]
        return order[np.argsort(high, kind="stable")]
    shift = max(int(e - 1).bit_length(), 1)
    if e == 0 or (max(n_pix, 1) << shift) >= 1 << 62:
        return np.argsort(flat, kind="stable")
    key = np.sort((flat << shift) | np.arange(e, dtype=np.int64))
    return key & ((1 << shift) - 1)


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

    def fired(self) -> np.ndarray:
        """(H, W) bool: the pixels with an event in the model."""
        out = np.zeros(self.height * self.width, bool)
        out[self.pix] = True
        return out.reshape(self.height, self.width)

    @classmethod
    def build(cls, events: EventStream, exposure: Exposure,
              hot_mask: np.ndarray | None = None, *,
              window: PixelEvents | None = None) -> EdiEvents:
        """Sort the window's events by pixel (stable: time order kept within a pixel).

        ``hot_mask`` (H, W) bool drops those pixels' events (their latent stays ``B``).
        ``window``: the same events already sorted (:class:`PixelEvents`), to skip the sort.
        """
        if window is None:
            window = PixelEvents.build(events, exposure)
        else:
            _check_window(window, exposure)
        window = window.without(hot_mask)
        h, w = window.height, window.width
        n_pix = h * w
        pix = window.pix
        T = float(exposure.duration_us)
        lead = np.ones(n_pix, np.float64)
        if len(pix) == 0:
            z = np.zeros(0)
            return cls(np.zeros(0, np.int64), z, z, np.zeros(0, np.int64), z, lead, w, h,
                       exposure, 0)
        ts = window.t_rel.astype(np.float64) / T
        ps = window.p.astype(np.int64)
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
        out = cls(pix, ts, ps.astype(np.float64), level, dur, lead, w, h, exposure, len(pix))
        out.__dict__["_runs"] = (pix[starts], group)  # the cached property, already at hand
        return out

    @cached_property
    def _runs(self) -> tuple[np.ndarray, np.ndarray]:
        """(pixels (U,) that fired, group (M,): which of them each event belongs to)."""
        if self.count == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        new = np.empty(self.count, bool)
        new[0] = True
        np.not_equal(self.pix[1:], self.pix[:-1], out=new[1:])
        return self.pix[new], np.cumsum(new) - 1

    @cached_property
    def _level_table_index(self) -> tuple[int, int, np.ndarray]:
        """(lowest level, highest, level − lowest): each event's place in a table of exp."""
        if self.count == 0:
            return 0, 0, np.zeros(0, np.int64)
        lo = int(self.level.min())
        return lo, int(self.level.max()), self.level - lo

    def integral(self, contrast: float) -> np.ndarray:
        """J = (1/T) ∫ exp(c·S(t)) dt per pixel: (H, W) float64, exact."""
        out = self.lead.copy()
        if self.count:
            out[self._runs[0]] = self.fired_integral(contrast)
        return out.reshape(self.height, self.width)

    def fired_integral(self, contrast: float) -> np.ndarray:
        """J of the pixels that fired (``sparse_levels``' pixels, in that order): (U,) float64,
        the same numbers as :meth:`integral` there (every other pixel's J is its ``lead``)."""
        pixels, group = self._runs
        if self.count == 0:
            return np.zeros(0, np.float64)
        lo, hi, idx = self._level_table_index
        table = _exp_table(lo, hi, contrast)
        if table is None:
            weights = self.dur * exp_levels(self.level, contrast)
        else:
            weights = self.dur * table[idx]
        # per fired pixel, in event order: the sums of a dense bincount, on U bins not H·W
        acc = np.bincount(group, weights=weights, minlength=len(pixels))
        return acc + self._lead_fired

    @cached_property
    def _lead_fired(self) -> np.ndarray:
        return self.lead[self._runs[0]]

    def sparse_levels(self, fractions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """S at instants (fractions of the window, clamped to [0, 1]) for the pixels that fired:
        ``(pixels (U,) flat indices, levels (K, U) int64)``; every other pixel's S is 0."""
        fr = np.clip(finite_instants(fractions), 0.0, 1.0)
        k = len(fr)
        pixels, group = self._runs
        u = len(pixels)
        if self.count == 0 or k == 0:
            return pixels, np.zeros((k, u), np.int64)
        order = np.argsort(fr, kind="stable")
        sorted_fr = fr[order]
        # the event's own time: an interval starts at the event, the step happens at it; an
        # event counts from the first instant at or after it. Counting the instants before it
        # is searchsorted(side="left") done as K comparisons, cheaper for a few instants
        # (counted in one byte where K allows: an eighth of the memory traffic of int64)
        slot = np.zeros(self.count, np.uint8 if k < 255 else np.int64)
        for f in sorted_fr:
            slot += self.time > f
        # signed steps per (sorted instant, fired pixel), summed over the instants: whole
        # numbers, so exact in any order
        index = slot.astype(np.int64)
        index *= u
        index += group
        steps = np.bincount(index, weights=self.step, minlength=(k + 1) * u)
        s_sorted = cumsum_rows(steps.reshape(k + 1, u)[:k].astype(np.int64))
        out = np.empty((k, u), np.int64)
        out[order] = s_sorted
        return pixels, out

    def levels_at(self, fractions: np.ndarray) -> np.ndarray:
        """S at instants given as fractions of the window (0 = start, 1 = end): (K, H, W).

        Only events inside the window count; instants outside ``[0, 1]`` are clamped.
        """
        pixels, s = self.sparse_levels(fractions)
        out = np.zeros((len(s), self.width * self.height), np.float64)
        out[:, pixels] = s
        return out.reshape(len(s), self.height, self.width)

    def latent(self, blurry: np.ndarray, fractions: np.ndarray, contrast: float) -> np.ndarray:
        """``L = B · exp(c·S(t)) / J`` at the given window fractions: (K, H, W[, 3]) float32."""
        ratio = self.ratio(fractions, contrast)
        if blurry.ndim == 3:
            return (ratio[..., None] * blurry[None]).astype(np.float32, copy=False)
        ratio *= blurry[None]
        return ratio

    def ratio(self, fractions: np.ndarray, contrast: float) -> np.ndarray:
        """``exp(c·S(t)) / J``: (K, H, W) float32, the factor applied to the blurry frame."""
        pixels, s = self.sparse_levels(fractions)
        k = len(s)
        # a silent pixel's J is 1 (its lead is the whole window): its factor is 1 at every
        # instant; the fired pixels' is exp(c·S)/J, 1/J between their steps
        out = np.ones((k, self.width * self.height), np.float32)
        if s.size:
            out[:, pixels] = (exp_levels(s, contrast) / self.fired_integral(contrast)
                              ).astype(np.float32)
        return out.reshape(k, self.height, self.width)


def cumsum_rows(a: np.ndarray) -> np.ndarray:
    """``np.cumsum(a, axis=0)`` in place, one row at a time: for a few long rows numpy's
    cumulative sum along the first axis is several times slower than K vector additions (the
    same additions in the same order)."""
    for j in range(1, len(a)):
        np.add(a[j], a[j - 1], out=a[j])
    return a


def _exp_table(lo: int, hi: int, contrast: float) -> np.ndarray | None:
    """``exp(c · level)`` for the whole levels lo … hi (None when the range is too wide)."""
    if hi - lo > 1 << 16:
        return None
    return np.exp(contrast * np.arange(lo, hi + 1, dtype=np.float64))


def exp_levels(level: np.ndarray, contrast: float) -> np.ndarray:
    """``exp(c · level)`` for whole-number levels, by table look-up (levels span a small range,
    so this replaces millions of ``exp`` calls by a gather)."""
    if level.size == 0:
        return np.ones(level.shape, np.float64)
    lo, hi = int(level.min()), int(level.max())
    table = _exp_table(lo, hi, contrast)
    if table is None:
        return np.exp(contrast * level.astype(np.float64))
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
    check_mask(hot_mask, w, h)
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
        if bins.ndim != 3 or bins.shape[0] == 0:
            raise ShapeError(f"bins have shape {bins.shape}, expected (M, H, W) with M ≥ 1")
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
        for fr in finite_instants(fractions):
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
