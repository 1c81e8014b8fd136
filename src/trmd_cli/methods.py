"""Deblurring methods: one small protocol, one registry.

A method turns a blurry frame and the events of its exposure into latent frames. Every method is
a :class:`Method`:

* it declares what it needs (:class:`MethodNeeds`: the contrast threshold c, the voxels' timing
  levels, trained weights);
* ``prepare`` settles what one exposure needs before the method runs — the window's events
  sorted per pixel, c (given, or estimated as EDI does), the hot-pixel mask — as a
  :class:`Prepared`;
* ``__call__`` runs it on raw events (instants in µs), ``from_bins`` on binned data (signed
  counts of M equal bins spanning the exposure, no event times: GOPRO-style voxels, LEDVDI's
  bins), both returning an :class:`Estimate`;
* ``for_recording`` and ``for_pattern`` give the same method (its loaded parts shared) with
  what was settled over a whole recording: one c, the sensor's fixed pattern
  (:mod:`trmd_cli.fixed_pattern`), removed from every blurry frame it is given.

:func:`make_method` builds the method a :class:`MethodConfig` names from :data:`REGISTRY`; a new
method is a class with a ``from_config`` class method and one entry there — ``trmd deblur``,
``trmd hfr`` and ``trmd eval`` then offer it. :data:`DEFAULT_METHOD` is the one constant to flip
when the default changes.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from .edi import EdiBins, EdiEvents, PixelEvents, check_blurry, hot_pixel_mask, propagate
from .errors import InputError, ShapeError
from .events import EventStream, Exposure, check_n
from .fixed_pattern import FixedPattern
from .isolated import bins_without_isolated, without_isolated
from .precision import PRECISIONS
from .threshold import RecordingContrast, search_contrast
from .voxel import resample_bins, scer_from_bins

__all__ = [
    "DEFAULT_METHOD",
    "DEFAULT_N",
    "CONTRAST_SCOPES",
    "METHODS",
    "MethodConfig",
    "MethodNeeds",
    "Prepared",
    "Estimate",
    "Method",
    "EdiMethod",
    "TrmdMethod",
    "MotionMethod",
    "FusedMethod",
    "motion_frames",
    "pattern_free",
    "deconv_noise",
    "REGISTRY",
    "make_method",
    "unavailable",
    "window_model",
]

#: the method used when none is asked for
DEFAULT_METHOD = "fused"
#: N used by EDI when none is given (2N+1 = 7 frames)
DEFAULT_N = 3
#: what an estimated contrast threshold is estimated over (see ``MethodConfig``)
CONTRAST_SCOPES = ("recording", "frame")


@dataclass(frozen=True)
class MethodConfig:
    """How to deblur.

    Attributes:
        method: a name of :data:`METHODS`.
        n: 2N+1 latent frames; None = 3 for EDI, the weights' N for TRMD.
        contrast: EDI's contrast threshold c; None = estimate it. TRMD uses it as an
            input when its weights take one (``prior="edi_c"``, as the shipped default) and to
            place frames at instants between its own (event integration).
        contrast_scope: when ``contrast`` is None: ``"recording"`` — the drivers that run a
            whole recording (``trmd deblur``, ``trmd hfr``) estimate one c for it from a few of
            its frames (:func:`trmd_cli.deblur.settle_recording`); ``"frame"`` — every frame
            its own. A method made from the config estimates per frame until it is settled.
        hot_pixels: ignore the events of hot pixels (see :func:`trmd_cli.edi.hot_pixel_mask`).
        drop_isolated: leave out of EDI's model the events that no neighbouring pixel
            corroborates (background activity, :mod:`trmd_cli.isolated`): EDI's frames, c's
            estimate and every method's use of them. The networks' voxels keep every event.
        fixed_pattern: the drivers that run a whole recording remove the APS sensor's fixed
            pattern, estimated over its frames, from every blurry frame
            (:func:`trmd_cli.deblur.settle_pattern`; where the scene did not move or the frames
            share no pattern, nothing is removed).
        weights, device, threads, precision: TRMD only (see ``TrmdEstimator.load``;
            ``precision="auto"`` runs the network in bfloat16 on CPUs that compute it natively
            — on the pinned validation set within 0.003 dB of float32).
        settle_contrast: settle c for every frame even when the method itself would not need
            it, so that it travels with each :class:`Estimate` (high-frame-rate streams fill
            the gaps between exposures by event integration, which needs it).
    """

    method: str = DEFAULT_METHOD
    n: int | None = None
    contrast: float | None = None
    contrast_scope: str = "recording"
    hot_pixels: bool = True
    drop_isolated: bool = True
    fixed_pattern: bool = True
    weights: str | Path | None = None
    device: str = "auto"
    threads: int | None = None
    precision: str = "auto"
    settle_contrast: bool = False

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise InputError(f"unknown method {self.method!r}",
                             hint="use `method` " + " or ".join(METHODS))
        check_n_contrast(self.n, self.contrast)
        if self.contrast_scope not in CONTRAST_SCOPES:
            raise InputError(f"unknown contrast scope {self.contrast_scope!r}",
                             hint="use `contrast_scope` " + " or ".join(CONTRAST_SCOPES))
        if self.precision not in PRECISIONS:
            raise InputError(f"unknown precision {self.precision!r}",
                             hint="use `precision` " + ", ".join(PRECISIONS))


def check_n_contrast(n, contrast) -> None:
    """Refuse an ``n`` that is not a whole number ≥ 1, or a ``contrast`` that is not a finite
    number > 0 (None: not given, for either)."""
    import numbers

    if n is not None:
        check_n(n)
    if contrast is not None and (isinstance(contrast, bool)
                                 or not isinstance(contrast, numbers.Real)
                                 or not (np.isfinite(contrast) and contrast > 0)):
        raise InputError(f"`contrast` must be a positive number or 'auto', got {contrast!r}")


@dataclass(frozen=True)
class MethodNeeds:
    """What a method needs for every frame.

    Attributes:
        contrast: the contrast threshold c, settled by ``prepare`` for every frame.
        timing: the voxels' sub-bin timing levels (:func:`trmd_cli.voxel.scer_levels`); on
            binned data the counts stand in for them.
        weights: trained weights, read when the method is built.
    """

    contrast: bool = False
    timing: bool = False
    weights: bool = False


@dataclass(frozen=True, eq=False)
class Prepared:
    """One exposure, settled before a method runs.

    Attributes:
        model: the window's events sorted per pixel (:class:`~trmd_cli.edi.EdiEvents`), or the
            binned twin (:class:`~trmd_cli.edi.EdiBins`) for binned data; ready for any c.
            Without the hot pixels' events and, unless kept, the isolated ones.
        contrast: c, the log-intensity step of one event.
        estimated: c came from :func:`trmd_cli.threshold.search_contrast` (else it was given).
        reliable: False when the window held too few events to estimate c (a default was used).
        hot: (H, W) bool, the pixels whose events are ignored; None when none are.
        note: what the user should know about c: why a default was used, or that the estimate
            sits at the search range's edge; None when there is nothing to say.
        window: the window's events sorted per pixel, hot pixels included
            (:class:`~trmd_cli.edi.PixelEvents`: the one sort the voxels and their timing levels
            reuse); None for binned data.
    """

    model: EdiEvents | EdiBins
    contrast: float
    estimated: bool = False
    reliable: bool = True
    hot: np.ndarray | None = None
    note: str | None = None
    window: PixelEvents | None = None

    @property
    def hot_pixels(self) -> int:
        """Number of pixels whose events are ignored."""
        return 0 if self.hot is None else int(self.hot.sum())


@dataclass(frozen=True, eq=False)
class Estimate:
    """Latent frames of one exposure.

    Attributes:
        frames: (K, H, W[, 3]) float32 [0, 1] intensity, not clipped.
        instants_us: (K,) float64, the time of each frame: µs, or fractions of the exposure
            (0 = start, 1 = end) for binned data.
        contrast: c used (EDI; TRMD's input or its in-between frames); None if none was needed.
        contrast_estimated: c came from :func:`trmd_cli.threshold.search_contrast`.
        contrast_reliable: False when too few events to estimate (a default was used).
        hot_pixels: number of pixels whose events were ignored.
        contrast_note: see :attr:`Prepared.note`.
        notes: other messages for the user (e.g. a method's fallback to EDI).
        fallback_contrast: the motion method's: c of the EDI frames it blended in where its
            deconvolution was not kept, fitted to that deconvolution
            (:func:`~trmd_cli.deconv.fit_contrast`); None: ``contrast``.
    """

    frames: np.ndarray
    instants_us: np.ndarray
    contrast: float | None
    contrast_estimated: bool = False
    contrast_reliable: bool = True
    hot_pixels: int = 0
    contrast_note: str | None = None
    notes: tuple[str, ...] = ()
    fallback_contrast: float | None = None

    @property
    def contrast_default(self) -> bool:
        """c is the default: it was to be estimated, and the window held too few events."""
        return self.contrast_estimated and not self.contrast_reliable


class Method(Protocol):
    """A deblurring method: blurry frame + the events of its exposure → latent frames."""

    name: str
    #: 2N+1 latent frames per exposure at its own instants
    n: int
    needs: MethodNeeds
    weights_hash: str | None
    #: the network's arithmetic as run; None for weight-free methods
    precision: str | None

    def prepare(self, blurry: np.ndarray, events: EventStream | np.ndarray,
                exposure: Exposure | None = None) -> Prepared:
        """Settle one exposure: ``events`` is the raw stream with ``exposure`` its window (µs),
        or (M, H, W) signed counts of M equal bins spanning the exposure."""
        ...

    def __call__(self, blurry: np.ndarray, events: EventStream, exposure: Exposure,
                 instants_us: np.ndarray | None = None) -> Estimate:
        """Latent frames at ``instants_us`` (µs; None = the method's 2N+1 instants)."""
        ...

    def from_bins(self, blurry: np.ndarray, bins: np.ndarray,
                  fractions: np.ndarray | None = None) -> Estimate:
        """Latent frames from binned data — ``bins`` (M, H, W) signed counts of M equal bins
        spanning the exposure, in time order — at ``fractions`` of the exposure (None = the
        2N+1 instants k/2N)."""
        ...

    def for_recording(self, recording: RecordingContrast) -> Method:
        """The method with one estimated c for every frame of a recording (the loaded parts
        shared, not copied)."""
        ...

    def for_pattern(self, pattern: FixedPattern | None) -> Method:
        """The method removing a recording's fixed pattern from every blurry frame (None: none;
        the loaded parts shared, not copied)."""
        ...


def _contrast_note(est) -> str | None:
    """What to tell the user about an estimated c (a :class:`ContrastEstimate`)."""
    from .threshold import CONTRAST_BOUNDS

    if not est.reliable:
        return f"{est.reason}; used the default c = {est.contrast:.3g}"
    if est.at_bound:
        lo, hi = CONTRAST_BOUNDS
        side = "lower" if est.contrast < (lo * hi) ** 0.5 else "upper"
        return (f"the estimated c = {est.contrast:.3f} sits at the {side} edge of the search "
                f"range {lo:g}–{hi:g}: the sensor's threshold may lie beyond it")
    return None


def bin_grid(n: int) -> np.ndarray:
    """The 2N+1 latent instants of binned data, as fractions of the exposure."""
    return np.linspace(0.0, 1.0, 2 * n + 1)


def bins_for(bins: np.ndarray, n: int) -> np.ndarray:
    """(M, H, W) counts as the 2N bins between the latent instants, float32
    (:func:`~trmd_cli.voxel.resample_bins` when M ≠ 2N)."""
    if bins.shape[0] == 2 * n:
        return np.asarray(bins, np.float32)
    return resample_bins(bins, 2 * n)


def own_bin_frames(n: int, fractions, who: str) -> np.ndarray:
    """The 2N+1 bin-grid fractions, or why a binned method cannot give ``fractions``."""
    grid = bin_grid(n)
    if fractions is not None and not (len(fractions) == len(grid)
                                      and np.allclose(fractions, grid)):
        # without event times there is nothing to propagate in-between frames with
        raise InputError(f"on binned data {who} gives its own {len(grid)} frames only",
                         hint="leave the instants out")
    return grid


def _check_bins(bins: np.ndarray) -> np.ndarray:
    bins = np.asarray(bins)
    if bins.ndim != 3 or bins.shape[0] == 0:
        raise ShapeError(f"bins have shape {bins.shape}, expected (M, H, W)")
    return bins


def _with_edi(method, edi: EdiMethod):
    """A shallow copy of ``method`` whose c is settled by ``edi`` (loaded parts shared)."""
    import copy

    out = copy.copy(method)
    out._edi = edi
    return out


class _RemovesPattern:
    """What every method shares: the recording's fixed pattern, removed from every blurry frame
    it is given (:meth:`for_pattern`; None: none)."""

    pattern: FixedPattern | None = None

    def for_pattern(self, pattern: FixedPattern | None):
        """A shallow copy of this method (loaded parts shared) that removes ``pattern`` from
        every blurry frame (None, or a pattern not removed: none)."""
        import copy

        out = copy.copy(self)
        out.pattern = pattern if pattern is not None and pattern.removed else None
        return out


def pattern_free(pattern: FixedPattern | None, blurry: np.ndarray) -> np.ndarray:
    """``blurry`` without ``pattern`` (``blurry`` itself without one)."""
    return blurry if pattern is None else pattern.removed_from(blurry)


def deconv_noise(blurry: np.ndarray, free: np.ndarray) -> float | None:
    """The noise σ the deconvolution of ``free`` — ``blurry`` without its fixed pattern — is
    weighed by: halfway, in variance, between B's as recorded and B's without the pattern (see
    :attr:`~trmd_cli.deconv.DeconvConfig.noise`); None when nothing was removed (σ measured on
    B as usual)."""
    if free is blurry:
        return None
    from .deconv import noise_level

    return math.sqrt(0.5 * (noise_level(blurry) ** 2 + noise_level(free) ** 2))


def _grid_match(exposure: Exposure, n: int, instants_us) -> tuple[np.ndarray, np.ndarray,
                                                                    np.ndarray, np.ndarray]:
    """``(grid, inst, nearest, exact)``: the 2N+1 instants (µs), the wanted ones (None = the
    grid), the grid frame nearest each, and whether it is on the grid (within ½ µs)."""
    grid = exposure.instants_us(n)
    inst = grid if instants_us is None else np.asarray(instants_us, np.float64)
    nearest = np.abs(inst[:, None] - grid[None]).argmin(axis=1)
    return grid, inst, nearest, np.isclose(inst, grid[nearest], atol=0.5)


def _without_ghosts(frames: np.ndarray, prep: Prepared, n: int) -> np.ndarray:
    """A network's 2N+1 frames with their ghosts replaced by what the events report
    (:func:`~trmd_cli.ghosts.without_ghosts`, with ``prep``'s c, hot pixels left out)."""
    from .ghosts import without_ghosts

    s = prep.model.levels_at(bin_grid(n))
    return without_ghosts(frames, (prep.contrast * (s - s[n])).astype(np.float32), n)


def _at_instants(frames: np.ndarray, events: EventStream, grid: np.ndarray, inst: np.ndarray,
                 nearest: np.ndarray, contrast: float, hot: np.ndarray | None) -> np.ndarray:
    """The grid's ``frames`` at ``inst``: each propagated from its nearest grid frame by event
    integration with ``contrast`` (:func:`~trmd_cli.edi.propagate`)."""
    out = np.empty((len(inst), *frames.shape[1:]), np.float32)
    for k in np.unique(nearest):
        sel = nearest == k
        out[sel] = propagate(frames[k], events, grid[k], inst[sel], contrast, hot)
    return out


def motion_frames(blurry: np.ndarray, events: EventStream, exposure: Exposure,
                  fractions: np.ndarray, prep: Prepared, motion=None,
                  noise: float | None = None):
    """The motion method on a settled exposure: ``(edi, res)`` — EDI's frames at
    ``fractions`` of the exposure and the guarded deconvolution
    (:class:`~trmd_cli.deconv.MotionDeblur`), both with ``prep``'s c and hot pixels; where
    that c was estimated, the EDI frames inside ``res`` have the c the deconvolution implies
    (its ``fallback_contrast``).
    ``motion``: a path to use instead of the estimate, its evidence already measured.
    ``noise``: the σ the deconvolution is weighed by when ``blurry`` had its fixed pattern
    removed (:func:`deconv_noise`; None: measured on ``blurry``)."""
    from .deconv import DeconvConfig, motion_deblur

    # EDI at the instants and at mid-exposure in one pass (one blur integral, not two)
    lat = prep.model.latent(blurry, np.append(fractions, 0.5), prep.contrast)
    edi, mid = lat[:-1], lat[-1]
    # an estimated c is refitted to the deconvolution for EDI's frames; a given one is kept
    refit = (lambda c: prep.model.latent(blurry, fractions, c)) if prep.estimated else None
    res = motion_deblur(blurry, events, exposure, fractions, edi, mid, prep.hot,
                        config=None if noise is None else DeconvConfig(noise=noise),
                        motion=motion, contrast=prep.contrast, edi_at=refit)
    return edi, res


def window_model(events: EventStream | np.ndarray, exposure: Exposure | None,
                 hot_pixels: bool, drop_isolated: bool = True
                 ) -> tuple[EdiEvents | EdiBins, np.ndarray | None, PixelEvents | None]:
    """What every method settles first for one exposure: ``(model, hot, window)`` — EDI's
    model of the window ready for any c, the hot-pixel mask (None when not asked for, and for
    binned data) and the window's per-pixel sort (None for binned data).

    Args:
        events: the raw stream with ``exposure`` its window (µs), or (M, H, W) signed counts
            of M equal bins spanning the exposure.
        drop_isolated: the model leaves out the events no neighbour corroborates
            (:mod:`trmd_cli.isolated`; after the hot pixels', whose events corroborate
            nothing); ``window`` keeps them.
    """
    if isinstance(events, EventStream):
        if exposure is None:
            raise InputError("raw events need their exposure window")
        key = (exposure, bool(hot_pixels), bool(drop_isolated))
        kept = _MODELS.get(id(events))
        if kept is not None and kept[0]() is events and kept[1] == key:
            return kept[2]
        window = PixelEvents.build(events, exposure)
        hot = hot_pixel_mask(events, exposure, window=window) if hot_pixels else None
        used = window.without(hot)
        if drop_isolated:
            used = without_isolated(used)
        model = (EdiEvents.build(events, exposure, window=used), hot, window)
        if id(events) not in _MODELS:
            weakref.finalize(events, _MODELS.pop, id(events), None)
        _MODELS[id(events)] = (weakref.ref(events), key, model)
        return model
    bins = _check_bins(events)
    return EdiBins.build(bins_without_isolated(bins) if drop_isolated else bins), None, None


#: the last window model of each event stream still alive, by identity: a frame the
#: recording's threshold was measured on is not sorted and tabulated again when it is
#: deblurred (the entry goes with the stream)
_MODELS: dict[int, tuple[weakref.ref, tuple, tuple]] = {}


class EdiMethod(_RemovesPattern):
    """EDI with a given, per-recording or per-frame estimated contrast threshold."""

    name = "edi"
    needs = MethodNeeds(contrast=True)
    weights_hash = None
    precision = None
    #: what the method is, for evaluation reports
    summary = ("EDI: contrast estimated per frame (a set's samples are independent), hot "
               "pixels and isolated events ignored (binned data: events spread evenly within "
               "each bin)")

    def __init__(self, n: int = DEFAULT_N, contrast: float | None = None,
                 hot_pixels: bool = True, *, recording: RecordingContrast | None = None,
                 drop_isolated: bool = True) -> None:
        check_n_contrast(n, contrast)
        self.n = n
        self.contrast = contrast
        self.hot_pixels = hot_pixels
        self.drop_isolated = drop_isolated
        #: where ``contrast`` came from when it was estimated over the recording, else None
        self.recording = recording

    @classmethod
    def from_config(cls, config: MethodConfig) -> EdiMethod:
        return cls(config.n or DEFAULT_N, config.contrast, config.hot_pixels,
                   drop_isolated=config.drop_isolated)

    def prepare(self, blurry, events, exposure=None) -> Prepared:
        """Sort the window's events per pixel (or integrate the bins) and settle c: the given
        one (or the recording's, :meth:`for_recording`), else
        :func:`~trmd_cli.threshold.search_contrast` on this frame. Binned data has no
        hot-pixel mask (the bins hold no per-event information to judge by)."""
        model, hot, window = window_model(events, exposure, self.hot_pixels,
                                          self.drop_isolated)
        if self.contrast is not None:
            return Prepared(model, self.contrast, self.recording is not None, hot=hot,
                            window=window)
        est = search_contrast(blurry, model)
        note = _contrast_note(est)
        if not est.reliable and window is not None and model.count < len(window):
            note += (f" (of the window's {len(window)} events, {len(window) - model.count} are "
                     "left out: hot pixels' (`hot_pixels=False` keeps them) or isolated "
                     "(`drop_isolated=False`))")
        return Prepared(model, est.contrast, True, est.reliable, hot, note, window)

    def for_recording(self, recording: RecordingContrast) -> EdiMethod:
        """This method with the recording's estimated c for every frame (reported as
        estimated, with no note per frame: the run says once where it came from)."""
        return EdiMethod(self.n, recording.contrast, self.hot_pixels, recording=recording,
                         drop_isolated=self.drop_isolated).for_pattern(self.pattern)

    def __call__(self, blurry, events, exposure, instants_us=None) -> Estimate:
        b = pattern_free(self.pattern, check_blurry(blurry, events.width, events.height))
        inst = exposure.instants_us(self.n) if instants_us is None else \
            np.asarray(instants_us, np.float64)
        prep = self.prepare(b, events, exposure)
        fr = (inst - exposure.start_us) / exposure.duration_us
        return Estimate(prep.model.latent(b, fr, prep.contrast), inst, prep.contrast,
                        prep.estimated, prep.reliable, prep.hot_pixels, prep.note)

    def from_bins(self, blurry, bins, fractions=None) -> Estimate:
        """EDI with the log intensity changing linearly within each bin (see
        :class:`~trmd_cli.edi.EdiBins`)."""
        bins = _check_bins(bins)
        b = pattern_free(self.pattern, check_blurry(blurry, bins.shape[2], bins.shape[1]))
        fr = bin_grid(self.n) if fractions is None else np.asarray(fractions, np.float64)
        prep = self.prepare(b, bins)
        return Estimate(prep.model.latent(b, fr, prep.contrast), fr, prep.contrast,
                        prep.estimated, prep.reliable, contrast_note=prep.note)


class TrmdMethod(_RemovesPattern):
    """TRMD (RE-Net residuals + reconstruction). Weights that take the threshold c get it given
    or estimated as EDI's; where c is settled, the frames' ghosts are replaced by what the
    events report (:mod:`trmd_cli.ghosts`); instants other than the 2N+1 are propagated from
    the nearest reconstructed frame by event integration (with the same c)."""

    name = "trmd"
    #: known before the weights are read; an instance's ``needs`` also says what they take
    needs = MethodNeeds(weights=True)
    summary = "RE-Net residuals + two-stage reconstruction, as `trmd deblur --method trmd`"

    def __init__(self, n: int | None = None, weights: str | Path | None = None,
                 device: str = "auto", threads: int | None = None,
                 contrast: float | None = None, hot_pixels: bool = True,
                 precision: str = "auto", *, settle_contrast: bool = False,
                 drop_isolated: bool = True) -> None:
        from .models.estimator import TrmdEstimator

        #: the loaded network (:class:`~trmd_cli.models.estimator.TrmdEstimator`)
        self.model = TrmdEstimator.load(weights, device=device, threads=threads, expect_n=n,
                                        precision=precision)
        self.n = self.model.n
        self.weights_hash = self.model.weights_hash
        #: the network's arithmetic as run: "fp32", "bf16" or "fp16" (mixed precision)
        self.precision = self.model.precision
        self.needs = MethodNeeds(contrast=self.model.needs_contrast or settle_contrast,
                                 timing=self.model.needs_timing, weights=True)
        self._edi = EdiMethod(self.n, contrast, hot_pixels, drop_isolated=drop_isolated)

    @classmethod
    def from_config(cls, config: MethodConfig) -> TrmdMethod:
        return cls(config.n, config.weights, config.device, config.threads, config.contrast,
                   config.hot_pixels, config.precision, settle_contrast=config.settle_contrast,
                   drop_isolated=config.drop_isolated)

    def prepare(self, blurry, events, exposure=None) -> Prepared:
        """c settled as EDI settles it (see :meth:`EdiMethod.prepare`)."""
        return self._edi.prepare(blurry, events, exposure)

    def for_recording(self, recording: RecordingContrast):
        """This method (the same loaded parts) with the recording's c for every frame."""
        return _with_edi(self, self._edi.for_recording(recording))

    def __call__(self, blurry, events, exposure, instants_us=None) -> Estimate:
        b = pattern_free(self.pattern, check_blurry(blurry, events.width, events.height))
        grid, inst, nearest, exact = _grid_match(exposure, self.n, instants_us)
        # in-between instants are propagated from the nearest frame with c: settle it for them
        settle = self.needs.contrast or not exact.all()
        prep = self.prepare(b, events, exposure) if settle else None
        c = None if prep is None else prep.contrast
        frames = self.grid_frames(b, events, exposure, prep)
        if prep is None:
            return Estimate(frames[nearest], inst, None)
        frames = _without_ghosts(frames, prep, self.n)
        if exact.all():
            return Estimate(frames[nearest], inst, c, prep.estimated, prep.reliable,
                            prep.hot_pixels, prep.note)
        out = _at_instants(frames, events, grid, inst, nearest, c, prep.hot)
        return Estimate(out, inst, c, prep.estimated, prep.reliable, prep.hot_pixels,
                        prep.note)

    def grid_frames(self, blurry: np.ndarray, events: EventStream, exposure: Exposure,
                    prep: Prepared | None) -> np.ndarray:
        """The network's 2N+1 frames (K, H, W[, 3]) of a checked blurry frame, with the
        exposure already settled by :meth:`prepare` (None when the weights take no c: the
        window is then sorted here)."""
        from .voxel import scer_levels, scer_voxels

        c = None if prep is None else prep.contrast
        # one per-pixel sort of the window for c, the voxels and their timing levels
        window = prep.window if prep is not None and prep.window is not None else \
            PixelEvents.build(events, exposure)
        levels = scer_levels(events, exposure, self.n, window=window) if self.needs.timing \
            else None
        return self.model(blurry, scer_voxels(events, exposure, self.n, window=window), c,
                          levels)

    def bin_frames(self, blurry: np.ndarray, bins: np.ndarray,
                   prep: Prepared | None) -> np.ndarray:
        """The network's 2N+1 frames (K, H, W[, 3]) of a checked blurry frame from checked
        bins (M, H, W), before the ghost check: M other than 2N resampled to 2N."""
        return self.model(blurry, scer_from_bins(bins_for(bins, self.n)),
                          None if prep is None else prep.contrast)

    def from_bins(self, blurry, bins, fractions=None) -> Estimate:
        """The network on SCER voxels made from the bins; its timing inputs, when it takes
        them, get the counts (no event times to refine them). M bins other than the network's
        2N are resampled to 2N (:func:`~trmd_cli.voxel.resample_bins`: whole bins summed when 2N
        divides M, else straddling bins split evenly); c is settled on the M bins as given."""
        bins = _check_bins(bins)
        b = pattern_free(self.pattern, check_blurry(blurry, bins.shape[2], bins.shape[1]))
        grid = own_bin_frames(self.n, fractions, "TRMD")
        prep = self.prepare(b, bins) if self.needs.contrast else None
        frames = self.bin_frames(b, bins, prep)
        if prep is None:
            return Estimate(frames, grid, None)
        frames = _without_ghosts(frames, prep, self.n)
        return Estimate(frames, grid, prep.contrast, prep.estimated, prep.reliable,
                        contrast_note=prep.note)


class MotionMethod(_RemovesPattern):
    """Non-blind deconvolution of the blurry frame along the global motion the events show
    (contrast maximisation, :mod:`trmd_cli.motion`; solver and guard, :mod:`trmd_cli.deconv`),
    anchored to EDI's middle frame and blended with EDI where the motion does not explain the
    blur or the events. The 2N+1 frames (and any other instants) are the recovered middle frame
    warped along the motion. c is settled as EDI settles it, for the fallback and the anchor."""

    name = "motion"
    needs = MethodNeeds(contrast=True)
    weights_hash = None
    precision = None
    summary = ("deconvolution along the events' global motion (contrast maximisation), "
               "guarded by EDI; contrast estimated per frame as EDI's")

    #: put before each of the motion's notes (a given motion says which one it is)
    note_prefix = ""

    def __init__(self, n: int = DEFAULT_N, contrast: float | None = None,
                 hot_pixels: bool = True, motion=None, *, drop_isolated: bool = True) -> None:
        """``motion``: a path to deconvolve along instead of the estimate (a
        :class:`~trmd_cli.motion.SampledMotion`, judged by the guard on each window's events
        as an estimate is)."""
        self.n = n
        self.motion = motion
        self._edi = EdiMethod(n, contrast, hot_pixels, drop_isolated=drop_isolated)

    @classmethod
    def from_config(cls, config: MethodConfig) -> MotionMethod:
        return cls(config.n or DEFAULT_N, config.contrast, config.hot_pixels,
                   drop_isolated=config.drop_isolated)

    def prepare(self, blurry, events, exposure=None) -> Prepared:
        """c settled as EDI settles it (see :meth:`EdiMethod.prepare`)."""
        return self._edi.prepare(blurry, events, exposure)

    def for_recording(self, recording: RecordingContrast):
        """This method (the same loaded parts) with the recording's c for every frame."""
        return _with_edi(self, self._edi.for_recording(recording))

    def __call__(self, blurry, events, exposure, instants_us=None) -> Estimate:
        recorded = check_blurry(blurry, events.width, events.height)
        b = pattern_free(self.pattern, recorded)
        noise = deconv_noise(recorded, b)
        inst = exposure.instants_us(self.n) if instants_us is None else \
            np.asarray(instants_us, np.float64)
        prep = self.prepare(b, events, exposure)
        fr = (inst - exposure.start_us) / exposure.duration_us
        given = None if self.motion is None else \
            self.motion.with_evidence(events, exposure, prep.hot)
        _, res = motion_frames(b, events, exposure, fr, prep, given, noise)
        if given is None:
            # from the second frame on, the tiles' votes are begun in a helper process while
            # this one estimates the global motion (:mod:`trmd_cli.helper_process`): started
            # after the first frame, so that a run of one frame does not pay for its start
            from . import helper_process

            helper_process.start()
        return Estimate(res.frames, inst, prep.contrast, prep.estimated, prep.reliable,
                        prep.hot_pixels, prep.note,
                        tuple(f"{self.note_prefix}{note}" for note in res.notes),
                        res.fallback_contrast)

    def from_bins(self, blurry, bins, fractions=None) -> Estimate:
        # (no flag named: deblur's is --method, eval's --methods)
        raise InputError("the motion method needs event times to estimate the motion; binned "
                         "events have none",
                         hint="use the fused method (the default: EDI's frames in the motion "
                              "method's place), edi or trmd")


class FusedMethod(_RemovesPattern):
    """TRMD and the motion method fused: per latent instant a small trained network
    (:mod:`trmd_cli.models.fusion`) corrects the motion method's frame from TRMD's, EDI's, B,
    the motion guard's weight and the events (:mod:`trmd_cli.fusion`); where the motion method
    fell back and no event fired, EDI's frame is kept. One c for all three, settled as EDI
    settles it; instants other than the 2N+1 are propagated from the nearest fused frame by
    event integration, as TRMD does."""

    name = "fused"
    needs = MethodNeeds(contrast=True, weights=True)
    summary = ("TRMD and the motion method fused by a small trained network; contrast "
               "estimated per frame as EDI's")

    def __init__(self, n: int | None = None, weights: str | Path | None = None,
                 device: str = "auto", threads: int | None = None,
                 contrast: float | None = None, hot_pixels: bool = True,
                 precision: str = "auto", fusion_weights: str | Path | None = None, *,
                 drop_isolated: bool = True) -> None:
        import torch

        from .models.fusion import default_fusion_path, load_fusion
        from .models.weights import weights_hash
        from .precision import resolve_precision

        self._trmd = TrmdMethod(n, weights, device, threads, contrast, hot_pixels, precision,
                                settle_contrast=True, drop_isolated=drop_isolated)
        self.n = self._trmd.n
        self.precision = self._trmd.precision
        fpath = default_fusion_path() if fusion_weights is None else Path(fusion_weights)
        #: the loaded fusion network (on the CPU: it is small) and its metadata
        self.fusion, self.fusion_meta = load_fusion(fpath)
        # channels-last, and bfloat16 where the CPU computes it natively (``precision``, as
        # for TRMD): 3.5× faster than float32 in the default layout (0.35 → 0.10 s for a
        # 346×260 frame's seven instants on 2 cores with AMX)
        self.fusion = self.fusion.to(memory_format=torch.channels_last)
        self._fusion_amp = resolve_precision(precision, torch.device("cpu"))
        self.weights_hash = f"{self._trmd.weights_hash}+{weights_hash(fpath)}"

    @staticmethod
    def missing_files() -> str | None:
        """Why this installation cannot run the method beyond RE-Net's weights (see
        :func:`unavailable`): the fusion network's weights do not ship; else None."""
        from .models.fusion import default_fusion_path

        if default_fusion_path().is_file():
            return None
        return ("this installation ships no fusion weights (weights_recipe/train_fusion.py "
                "makes them)")

    @classmethod
    def from_config(cls, config: MethodConfig) -> FusedMethod:
        return cls(config.n, config.weights, config.device, config.threads, config.contrast,
                   config.hot_pixels, config.precision, drop_isolated=config.drop_isolated)

    def prepare(self, blurry, events, exposure=None) -> Prepared:
        """c settled as EDI settles it (see :meth:`EdiMethod.prepare`)."""
        return self._trmd.prepare(blurry, events, exposure)

    def for_recording(self, recording: RecordingContrast):
        """This method (the same loaded parts) with the recording's c for every frame."""
        import copy

        out = copy.copy(self)
        out._trmd = self._trmd.for_recording(recording)
        return out

    def __call__(self, blurry, events, exposure, instants_us=None) -> Estimate:
        from .fusion import fusion_inputs, motion_where_trusted
        from .models.fusion import MAX_CONTRAST, MAX_FALLBACK_CONTRAST

        recorded = check_blurry(blurry, events.width, events.height)
        b = pattern_free(self.pattern, recorded)
        noise = deconv_noise(recorded, b)
        grid, inst, nearest, exact = _grid_match(exposure, self.n, instants_us)
        prep = self.prepare(b, events, exposure)
        # the motion method's own fallbacks ("used EDI") are not this method's: where the
        # motion is not used the network leans on TRMD, so they are not passed on
        notes: tuple[str, ...] = ()
        if prep.contrast <= MAX_FALLBACK_CONTRAST:
            ins = fusion_inputs(b, events, exposure, self._trmd, self.n, prep, noise)
            frames = self._fuse(ins)
            if prep.contrast > MAX_CONTRAST:
                # beyond the c at which the network saw motion frames, it is trusted where the
                # motion method fell back (its input there, EDI's frames, is the one it saw on
                # the still cameras of its training set, up to this c), not where it did not
                frames = motion_where_trusted(frames, ins.motion, ins.weight)
        else:
            # the network is not run, so neither is TRMD, which only it reads
            fr = np.arange(2 * self.n + 1) / (2 * self.n)
            frames = motion_frames(b, events, exposure, fr, prep, noise=noise)[1].frames
            notes = (f"c = {prep.contrast:.2f} is beyond the fusion network's sensors "
                     f"(c ≤ {MAX_FALLBACK_CONTRAST}): the motion method's frames",)
        frames = np.ascontiguousarray(frames, np.float32)
        frames = frames[nearest] if exact.all() else \
            _at_instants(frames, events, grid, inst, nearest, prep.contrast, prep.hot)
        return Estimate(frames, inst, prep.contrast, prep.estimated, prep.reliable,
                        prep.hot_pixels, prep.note, notes)

    def _fuse(self, ins) -> np.ndarray:
        """The fused frames (K, H, W[, 3]) float32 from the network's inputs
        (:class:`~trmd_cli.fusion.FusionInputs`): the network's, and EDI's where nothing
        moved (:func:`~trmd_cli.fusion.keep_where_quiet`)."""
        import torch

        from .fusion import keep_where_quiet
        from .models.fusion import fusion_planes
        from .precision import autocast

        planes = fusion_planes(ins.motion, ins.trmd, ins.edi, ins.blurry, ins.weight,
                               ins.events, self.n)
        with torch.inference_mode():
            # one instant at a time: a batch of all 2N+1 makes activations of 40–120 MB,
            # above what the C heap keeps (32 MiB), so every frame mapped them afresh
            # and faulted in each page (12.6 M page faults over davis346's 59 frames)
            with autocast(torch.device("cpu"), self._fusion_amp):
                out = torch.cat([self.fusion(p.contiguous(memory_format=torch.channels_last))
                                 for p in planes.split(1)])
            out = out[:, 0].float().numpy()
        k = ins.motion.shape[0]
        frames = out.reshape(k, *ins.motion.shape[3:], *out.shape[1:])
        if ins.motion.ndim == 4:  # (K, C, H, W) → (K, H, W, C)
            frames = frames.transpose(0, 2, 3, 1)
        return keep_where_quiet(np.ascontiguousarray(frames, np.float32), ins.edi, ins.weight,
                                ins.fired)

    def from_bins(self, blurry, bins, fractions=None) -> Estimate:
        """Binned events hold no event times to find a motion in: the network is given the
        motion method's fallback, EDI's frames with a weight of 0, beside TRMD's frames
        (:func:`~trmd_cli.fusion.fusion_inputs_from_bins`), as it saw wherever the guard fell
        back in training. On the pinned set binned from its events, over TRMD's frames (PSNR
        middle / sequence): 18 bins 31.19 / 29.22 → 31.15 / 30.00 dB, 6 bins 31.10 / 29.06 →
        31.04 / 29.99. Beyond the c it saw such inputs at (above
        :data:`~trmd_cli.models.fusion.MAX_FALLBACK_CONTRAST`): TRMD's frames."""
        from .fusion import fusion_inputs_from_bins
        from .models.fusion import MAX_FALLBACK_CONTRAST

        bins = _check_bins(bins)
        b = pattern_free(self.pattern, check_blurry(blurry, bins.shape[2], bins.shape[1]))
        grid = own_bin_frames(self.n, fractions, "the fused method")
        prep = self.prepare(b, bins)
        said = "binned events have no event times to estimate the motion from"
        if prep.contrast > MAX_FALLBACK_CONTRAST:
            frames = _without_ghosts(self._trmd.bin_frames(b, bins, prep), prep, self.n)
            note = (f"{said}, and c = {prep.contrast:.2f} is beyond the fusion network's "
                    f"sensors (c ≤ {MAX_FALLBACK_CONTRAST} on binned data): TRMD's frames")
        else:
            frames = self._fuse(fusion_inputs_from_bins(b, bins, self._trmd, self.n, prep))
            note = f"{said}: fused with EDI's frames in its place"
        return Estimate(frames, grid, prep.contrast, prep.estimated, prep.reliable,
                        contrast_note=prep.note, notes=(note,))


#: every deblurring method's class by name: the one place a method is added. A class has
#: ``name``, ``needs`` (what is known before it is built), ``summary`` (one line for reports)
#: and ``from_config(config)``.
REGISTRY: dict[str, type] = {cls.name: cls for cls in (EdiMethod, TrmdMethod, MotionMethod,
                                                      FusedMethod)}
#: every deblurring method, in the order messages list them
METHODS = tuple(REGISTRY)


def make_method(config: MethodConfig) -> Method:
    """The method ``config.method`` names (TRMD loads its weights once, here), with
    ``config.threads`` (when given) as the process's thread count: torch's, which the
    weight-free methods' products and helper process follow too (:mod:`trmd_cli.threads`)."""
    if config.threads is not None:
        from .threads import set_threads

        set_threads(config.threads)
    return REGISTRY[config.method].from_config(config)


def unavailable(config: MethodConfig) -> str | None:
    """Why ``config``'s method cannot run in this installation, or None: it needs weights,
    none are given, and none ship."""
    missing = getattr(REGISTRY[config.method], "missing_files", None)
    why = missing() if missing is not None else None
    if why:
        return why
    if not REGISTRY[config.method].needs.weights or config.weights is not None:
        return None
    from .models.weights import default_weights_path

    if default_weights_path().is_file():
        return None
    return ("this installation ships no trained weights; pass `weights=PATH` to a .safetensors "
            "file from `trmd train`")
