"""Contrast-threshold estimation for EDI, one exposure at a time.

Why not the classic energies: total variation always prefers the smallest ``c`` (a blurrier
latent has less variation), and sparse-gradient priors prefer it too (EDI's own noise and the
recovered texture grow with ``c``); a binarised-edge cross-correlation picked c ≈ 0.11 for a
true 0.2 in our trials.

What is used instead — *event–gradient consistency*. Around an instant f, the signed event
count of a short window ``[f − δ, f + δ]`` is the change of log intensity over that window
divided by c; by brightness constancy that change is ``−∇log L(f) · v · 2δ``. So within a small
block where the image motion v is about constant, the count map D must be a *linear* function
of the two gradient images of ``log L(f)``. With the right c, ``L(f)`` is sharp and its
gradients sit where the events fire: the least-squares fit of D on (∂x, ∂y) per block is good.
With c too small the gradients are smeared over the blur path; with c too large EDI paints
ghost edges where nothing fires; either way the fit gets worse. The energy is the fraction of
``Σ D²`` the per-block fits leave unexplained, summed over a few instants; it does not depend on
the scale of D, so c enters only through the shape of the latent's gradients.

On simulated frames with a known threshold (``trmd_cli.simulate``, clean and DAVIS-like
sensors, eight images) the chosen c gives a middle frame on average within 0.3 dB of the one
obtained with the true c (``bench/bench_edi.py`` prints the figure).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cache

import numpy as np

from .edi import EdiBins, EdiEvents, check_blurry
from .errors import InputError
from .events import EventStream, Exposure
from .signals import shielded

__all__ = [
    "ContrastEstimate",
    "ContrastObjective",
    "RecordingContrast",
    "block_fit",
    "explained_share",
    "estimate_contrast",
    "search_contrast",
    "search_contrast_pooled",
    "MIN_EVENTS",
    "INSTANTS",
    "DEFAULT_CONTRAST",
    "CONTRAST_BOUNDS",
]

#: used when a window holds too few events to estimate from (DAVIS346 at default biases)
DEFAULT_CONTRAST = 0.25
#: search range of the estimate
CONTRAST_BOUNDS = (0.05, 1.0)
#: instants (fractions of the exposure) at which the consistency is measured
INSTANTS = np.array([0.2, 0.35, 0.5, 0.65, 0.8])
#: half-width δ of the event window around each instant, fraction of the exposure
_DELTA = 0.03
#: block size (px) over which the image motion is taken as constant
_BLOCK = 16
#: Gaussian σ (px) applied to both the event counts and the latent's log before the gradients
_SIGMA = 1.5
#: offset in log(L + eps): keeps dark, noisy pixels from dominating the gradients
_EPS = 0.02
#: fewer events than this per window → no estimate (DEFAULT_CONTRAST is used)
MIN_EVENTS = 2000
#: the largest c·|S| (log-intensity change) computed in float32: exp(88.7) is its largest
#: number, and a pixel whose events sum further (one the hot-pixel test missed, a flicker)
#: made the energy NaN at a high c; such an exposure is computed in float64
_FLOAT32_EXP = 80.0


@dataclass(frozen=True)
class ContrastEstimate:
    """Result of :func:`search_contrast`.

    Attributes:
        contrast: the chosen c (``DEFAULT_CONTRAST`` when not ``reliable``).
        reliable: False when the window held too few events to estimate from.
        energy: the consistency energy at ``contrast`` (lower is better; nan if unreliable).
        evaluations: number of energy evaluations spent.
        at_bound: the best c lies at an end of the search range: the true threshold may lie
            beyond it, or the energy has no minimum for this frame (a warning, not an error).
        reason: why no estimate was made (``reliable`` False), for the user; None otherwise.
    """

    contrast: float
    reliable: bool
    energy: float
    evaluations: int
    at_bound: bool = False
    reason: str | None = None


@dataclass(frozen=True)
class RecordingContrast:
    """One contrast threshold for a whole recording (:func:`search_contrast_pooled`): one
    sensor, one threshold, estimated on a few of its frames together.

    Attributes:
        contrast: the chosen c.
        frames: names of the frames it was estimated from.
        energy: the pooled consistency energy at ``contrast``.
        evaluations: energy evaluations spent (each one on every frame of ``frames``).
        at_bound: the best c lies at an end of the search range (see
            :attr:`ContrastEstimate.at_bound`).
    """

    contrast: float
    frames: tuple[str, ...]
    energy: float
    evaluations: int
    at_bound: bool = False


class ContrastObjective:
    """The event–gradient consistency energy of one exposure as a function of c.

    Build once per exposure (:meth:`from_events` or :meth:`from_bins`: sorting and counting),
    then call with any c (each call: one EDI evaluation at a few instants, two separable filters
    per instant and block sums on a half-resolution grid).

    Args:
        model: :class:`~trmd_cli.edi.EdiEvents` or :class:`~trmd_cli.edi.EdiBins` (anything with
            ``integral(c)`` and ``levels_at(fractions)``).
        blurry: (H, W) or (H, W, 3) float32.
        instants: (K,) fractions of the window where the consistency is measured.
        counts: K (H, W) signed event counts of a short window around each instant.
    """

    def __init__(self, model, blurry: np.ndarray, instants: np.ndarray,
                 counts: list[np.ndarray]) -> None:
        self.model = model
        self.blurry = _gray(blurry)
        h, w = self.blurry.shape
        self.hb, self.wb = _whole_blocks(h, w)
        if self.hb == 0 or self.wb == 0:
            raise InputError(f"a {w}x{h} frame is too small to estimate the contrast threshold "
                             f"(needs at least {_BLOCK}x{_BLOCK})", hint="pass `contrast=C`")
        self._blocks = (self.wb // _BLOCK, self.hb // _BLOCK)  # cv2 size order: (w, h)
        # S in half steps so that the bins' mid-bin levels stay whole numbers: exp by look-up
        self._pixels = None
        if hasattr(model, "sparse_levels"):
            # raw events: whole levels, and only the pixels that fired differ from the base
            self._pixels, s = model.sparse_levels(instants)
            twice = 2 * s
            self._lookup = True
            # per instant, the fired pixels whose S is not 0 there (the others keep the base),
            # as flat pixel indices, and their S
            moved = [np.flatnonzero(row) for row in s]
            self._moved = moved
            self._moved_pixels = [self._pixels[m] for m in moved]
            # a silent pixel's J is exactly 1, so its latent is B at every c: its log is taken
            # once here, and an evaluation computes the fired pixels' only
            self._blurry_fired = self.blurry.reshape(-1)[self._pixels]
            self._log_silent = np.log(self.blurry + np.float32(_EPS))
        else:
            twice = 2.0 * model.levels_at(instants)
            self._lookup = bool(np.allclose(twice, np.rint(twice), atol=1e-6))
        if self._lookup:
            lv = twice if twice.dtype.kind == "i" else np.rint(twice).astype(np.int64)
            self._lo = int(min(lv.min(), 0)) if lv.size else 0
            self._hi = int(max(lv.max(), 0)) if lv.size else 0
            self.levels = (lv - self._lo).astype(np.int32)
            if self._pixels is not None:
                self._moved_levels = [self.levels[k, m] for k, m in enumerate(moved)]
        else:
            self.levels = (twice / 2).astype(np.float32)
        #: the largest |S| (events) at an instant: bounds the exponent of every c
        self._reach = float(np.abs(twice).max()) / 2 if twice.size else 0.0
        self.counts = [_smoothed(c, self.hb, self.wb) for c in counts]
        self.total = float(sum(_block_means(c * c, self._blocks).sum() for c in self.counts))
        self.evaluations = 0

    @classmethod
    def from_events(cls, prep: EdiEvents, blurry: np.ndarray,
                    instants: np.ndarray | None = None) -> ContrastObjective:
        """``instants``: fractions of the window to measure at (None: the usual five)."""
        h, w = prep.height, prep.width
        instants = INSTANTS if instants is None else np.asarray(instants, np.float64)
        counts = []
        for f in instants:
            sel = np.abs(prep.time - f) <= _DELTA
            d_map = np.bincount(prep.pix[sel], weights=prep.step[sel], minlength=h * w)
            counts.append(d_map.reshape(h, w))
        return cls(prep, blurry, instants, counts)

    @classmethod
    def from_bins(cls, model: EdiBins, blurry: np.ndarray,
                  instants: np.ndarray | None = None) -> ContrastObjective:
        """Instants at the centres of the bins nearest to the usual ones (or to ``instants``,
        fractions of the exposure); counts = those bins."""
        m = model.bins.shape[0]
        f0, f1 = model.exposure
        instants = INSTANTS if instants is None else np.asarray(instants, np.float64)
        wanted = f0 + instants * (f1 - f0)
        idx = sorted({min(max(int(np.floor(f * m)), 0), m - 1) for f in wanted})
        instants = (np.array(idx) + 0.5) / m
        return cls(model, blurry, instants, [model.bins[j] for j in idx])

    def __call__(self, contrast: float) -> float:
        return 1.0 - self.explained(contrast) / self.total

    def explained(self, contrast: float) -> float:
        """The part of ``total`` (Σ D² over the blocks) the per-block fits explain at c."""
        self.evaluations += 1
        ft = np.float64 if contrast * self._reach > _FLOAT32_EXP else np.float32
        if self._lookup:
            table = np.exp(ft(contrast / 2) * np.arange(self._lo, self._hi + 1, dtype=ft))
        if self._pixels is not None:
            # B / J on the fired pixels (elsewhere J = 1); where S = 0 (every silent pixel,
            # and fired ones between their steps) the latent is that base (exp(0) = 1): its
            # log is computed once, not per instant
            base_fired = self._blurry_fired / self.model.fired_integral(contrast).astype(ft)
            log_base = self._log_silent.copy()
            log_base.reshape(-1)[self._pixels] = np.log(base_fired + ft(_EPS))
        else:
            base = self.blurry / self.model.integral(contrast).astype(ft)
        num = 0.0
        for k, d in enumerate(self.counts):
            if self._pixels is not None:
                log_l = log_base.copy()
                log_l.reshape(-1)[self._moved_pixels[k]] = np.log(
                    base_fired[self._moved[k]] * table[self._moved_levels[k]] + ft(_EPS))
            else:
                if self._lookup:
                    lat = base * table[self.levels[k]]
                else:
                    lat = base * np.exp(ft(contrast) * self.levels[k])
                log_l = np.log(lat + ft(_EPS)).astype(np.float32, copy=False)
            num += block_fit(*_gradients(log_l, self.hb, self.wb), d, self._blocks)
        return num


def _gray(image: np.ndarray) -> np.ndarray:
    """(H, W) float32: the image, or a colour image's luma."""
    gray = image if image.ndim == 2 else image @ np.array([0.299, 0.587, 0.114], np.float32)
    return gray.astype(np.float32)


def _whole_blocks(h: int, w: int) -> tuple[int, int]:
    """The rows and columns of whole blocks (even, so that the half-resolution grid has whole
    blocks too)."""
    return (h // _BLOCK) * _BLOCK, (w // _BLOCK) * _BLOCK


@cache
def _kernels() -> tuple[np.ndarray, np.ndarray]:
    """The Gaussian (σ = :data:`_SIGMA`) as a column, and its derivative: blur and central
    difference in one separable pass."""
    import cv2

    kernel = cv2.getGaussianKernel(int(2 * round(3 * _SIGMA) + 1), _SIGMA).astype(np.float32)
    d = np.array([-0.5, 0.0, 0.5], np.float32)
    return kernel, np.convolve(kernel[:, 0], d, mode="same").astype(np.float32)


def _smoothed(counts: np.ndarray, hb: int, wb: int) -> np.ndarray:
    """Signed counts smoothed by the Gaussian, on the half-resolution grid of whole blocks."""
    import cv2

    gauss, _ = _kernels()
    return np.ascontiguousarray(cv2.sepFilter2D(np.asarray(counts, np.float32), -1, gauss,
                                                gauss)[:hb:2, :wb:2])


def _gradients(log_l: np.ndarray, hb: int, wb: int) -> tuple[np.ndarray, np.ndarray]:
    """The smoothed x and y gradients of a log-intensity image on the half-resolution grid:
    blurred gradients are band-limited, every second pixel carries the information."""
    import cv2

    gauss, dgauss = _kernels()
    return (cv2.sepFilter2D(log_l, -1, dgauss, gauss)[:hb:2, :wb:2],
            cv2.sepFilter2D(log_l, -1, gauss, dgauss)[:hb:2, :wb:2])


def _block_means(img: np.ndarray, blocks: tuple[int, int]) -> np.ndarray:
    """Per-block means of ``img``'s planes (its channels, up to four at once) by area
    resampling: exact for whole blocks, much faster than a reshape-sum. The common factor
    (the block's area) cancels in the 2×2 solve and in the energy's ratio."""
    import cv2

    return cv2.resize(img, blocks, interpolation=cv2.INTER_AREA).astype(np.float64)


def explained_share(image: np.ndarray, counts: np.ndarray) -> float:
    """How well a frame's edges sit where the events fired, at the events' scale: the share of
    ``Σ D²`` that the consistency energy's per-block fits on this frame's log gradients explain
    (1 − the energy, with the frame given instead of EDI's), ``D`` the signed event counts of a
    short window around the frame's instant.

    A blurry frame's gradients are smeared along the motion and explain little; noise has
    gradients but none that follow the events, so unlike a gradient energy it does not raise
    the figure. EDI builds its frames from the events themselves, which favours it.

    Args:
        image: (H, W) or (H, W, 3) [0, 1] intensity at the window's middle.
        counts: (H, W) signed event counts of the window (the energy's windows are ±0.03 of
            the exposure).
    Returns:
        In [0, 1]; nan where no event is left after smoothing or the frame holds no whole
        16×16 block.
    """
    gray = _gray(image)
    hb, wb = _whole_blocks(*gray.shape)
    if hb == 0 or wb == 0:
        return float("nan")
    blocks = (wb // _BLOCK, hb // _BLOCK)
    d = _smoothed(counts, hb, wb)
    total = float(_block_means(d * d, blocks).sum())
    if total <= 0:
        return float("nan")
    log_l = np.log(np.clip(gray, 0.0, None) + np.float32(_EPS))
    return block_fit(*_gradients(log_l, hb, wb), d, blocks) / total


def block_fit(gx: np.ndarray, gy: np.ndarray, d: np.ndarray, blocks: tuple[int, int]) -> float:
    """The part of ``Σ d²`` that per-block least-squares fits ``d ≈ vx·gx + vy·gy`` explain,
    summed over the blocks (each block's fitted ``Σ d²``), up to the blocks' common area.

    Args:
        gx, gy, d: (h, w) float32 planes of whole blocks: the gradients of log intensity and
            the signed event counts of a short window, each smoothed alike.
        blocks: the number of blocks ``(across, down)`` (cv2's size order).
    """
    import cv2

    # contiguous planes, interleaved by cv2.merge: faster than strided products into the
    # channels of one image, and the same numbers
    gx, gy = np.ascontiguousarray(gx), np.ascontiguousarray(gy)
    four = cv2.merge([gx * gx, gy * gy, gx * gy, gx * d])
    sxx, syy, sxy, sxd = np.moveaxis(_block_means(four, blocks), -1, 0)
    syd = _block_means(gy * d, blocks)
    det = sxx * syy - sxy * sxy
    ok = det > 1e-9 * (sxx + syy) ** 2 + 1e-30
    det = np.where(ok, det, 1.0)
    explained = np.where(ok, (syy * sxd * sxd - 2 * sxy * sxd * syd + sxx * syd * syd) / det,
                         0.0)
    return float(explained.sum())


#: points of the coarse grid over the search range (log scale: steps of ×2.1 over 0.05–1)
_COARSE = 5
#: rounds of refinement: each evaluates the two points half a step either side of the best
_ROUNDS = 2


def search_contrast(blurry: np.ndarray, prep: EdiEvents | EdiBins,
                    bounds: tuple[float, float] = CONTRAST_BOUNDS) -> ContrastEstimate:
    """Minimise the consistency energy over c in ``bounds`` (log scale).

    The energy is not guaranteed unimodal over the whole range, so a coarse grid brackets the
    minimum first; two rounds of half steps around the best point so far and a parabola through
    the best point and its neighbours refine it (9 evaluations in all, none repeated). On the
    40 frames of ``bench/bench_threshold_search.py`` the result lies within 1.1 % of the minimum
    of a 49-point grid; a grid of 8 refined by a finer grid of 5 (13 evaluations) came within
    6.7 % only: its finer grid repeats the best coarse point, and a parabola through two
    coincident points leaves c on the coarse grid.
    """
    lo, hi = bounds
    if not (0 < lo < hi < np.inf):
        raise InputError(f"contrast search bounds {bounds} must satisfy 0 < low < high < ∞")
    if isinstance(prep, EdiBins):
        count = int(np.abs(prep.bins).sum())
        if count < MIN_EVENTS:
            return _fallback(f"too few events ({count}, at least {MIN_EVENTS} needed)")
        obj = ContrastObjective.from_bins(prep, blurry)
    else:
        if prep.count < MIN_EVENTS:
            return _fallback(f"too few events ({prep.count}, at least {MIN_EVENTS} needed)")
        obj = ContrastObjective.from_events(prep, blurry)
    if obj.total <= 0:
        return _fallback("no events near the instants where the threshold is measured: are "
                         "all events at one instant? (check `time_unit`)")
    x, energy, at_bound = _minimise(lambda g: obj(float(np.exp(g))), np.log(lo), np.log(hi))
    return ContrastEstimate(float(np.exp(x)), True, energy, obj.evaluations, at_bound=at_bound)


def search_contrast_pooled(objectives: list[ContrastObjective],
                           bounds: tuple[float, float] = CONTRAST_BOUNDS
                           ) -> tuple[float, float, bool, int]:
    """One c for several exposures of one sensor: the search of :func:`search_contrast` on
    their pooled energy, ``1 − Σ explained / Σ total`` (exposures weigh by their events' Σ D²,
    so a busy frame counts more than a quiet one). One objective gives exactly
    :func:`search_contrast`'s result.

    Returns:
        ``(c, energy at c, whether c is at an end of bounds, evaluations per objective)``.
    """
    lo, hi = bounds
    if not (0 < lo < hi < np.inf):
        raise InputError(f"contrast search bounds {bounds} must satisfy 0 < low < high < ∞")
    if not objectives:
        raise InputError("no exposure to estimate the contrast threshold from")
    total = sum(o.total for o in objectives)
    # the exposures' parts of one evaluation on two threads (their filters and products
    # release the GIL), summed in the exposures' order: the same number as one by one
    with ThreadPoolExecutor(max_workers=min(2, len(objectives))) as pool:

        def pooled(g: float) -> float:
            c = float(np.exp(g))
            # a Ctrl-C is held while the pool's and the futures' locks are taken (one
            # evaluation, a fraction of a second; see trmd_cli.signals.shielded)
            with shielded():
                return 1.0 - sum(pool.map(lambda o: o.explained(c), objectives)) / total

        before = objectives[0].evaluations
        x, energy, at_bound = _minimise(pooled, np.log(lo), np.log(hi))
    return float(np.exp(x)), energy, at_bound, objectives[0].evaluations - before


def _minimise(energy, low: float, high: float) -> tuple[float, float, bool]:
    """The minimiser of ``energy`` over [low, high] as :func:`search_contrast` finds it:
    ``(x, energy at the best point evaluated, whether that point is an end of the range)``."""
    xs, fs = _refined_grid(energy, low, high)
    k = int(np.argmin(fs))
    best_x, best_f = float(xs[k]), float(fs[k])
    at_bound = k in (0, len(xs) - 1)
    if 0 < k < len(xs) - 1:
        x0, x1, x2 = xs[k - 1: k + 2]
        f0, f1, f2 = fs[k - 1: k + 2]
        denom = (x1 - x0) * (f1 - f2) - (x1 - x2) * (f1 - f0)
        if denom != 0:
            x = x1 - 0.5 * ((x1 - x0) ** 2 * (f1 - f2) - (x1 - x2) ** 2 * (f1 - f0)) / denom
            if x0 < x < x2:
                best_x = float(x)
    return best_x, best_f, at_bound


def _refined_grid(energy, low: float, high: float) -> tuple[np.ndarray, np.ndarray]:
    """The points (sorted) and energies of the coarse grid over [low, high] and its rounds of
    refinement: every point is evaluated once, none outside the range."""
    xs = list(np.linspace(low, high, _COARSE))
    fs = [energy(x) for x in xs]
    step = xs[1] - xs[0]
    for _ in range(_ROUNDS):
        step /= 2
        best = xs[int(np.argmin(fs))]
        for x in (best - step, best + step):
            if low <= x <= high:
                xs.append(x)
                fs.append(energy(x))
    order = np.argsort(xs)
    return np.asarray(xs)[order], np.asarray(fs)[order]


def _fallback(reason: str) -> ContrastEstimate:
    return ContrastEstimate(DEFAULT_CONTRAST, False, float("nan"), 0, reason=reason)


def estimate_contrast(blurry: np.ndarray, events: EventStream, exposure: Exposure, *,
                      hot_mask: np.ndarray | None = None,
                      bounds: tuple[float, float] = CONTRAST_BOUNDS) -> float:
    """Estimate EDI's contrast threshold c for one blurry frame and its events.

    Args:
        blurry: (H, W) or (H, W, 3) float32 [0, 1] (colour is reduced to luma).
        events: the stream; events of ``exposure`` are used.
        exposure: the exposure window, µs.
        hot_mask: optional (H, W) bool of pixels to ignore.
        bounds: search range of c.

    Returns:
        c > 0; :data:`DEFAULT_CONTRAST` when the window has too few events to tell (use
        :func:`search_contrast` to know whether that happened).
    """
    b = check_blurry(blurry, events.width, events.height)
    prep = EdiEvents.build(events, exposure, hot_mask)
    return search_contrast(b, prep, bounds).contrast
