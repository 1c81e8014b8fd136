"""The per-frame loop: run a method over every frame of a source, one exposure at a time.

Never prints: warnings travel with each :class:`FrameResult`; the CLI says them. A window
without events is passed through (the blurry frame repeated), not an error: a few frames of a
long recording often miss their events.

Binned items (:class:`~trmd_cli.read.folders.BinnedWindow`: no event times) go through the same
loop to the method's ``from_bins``; their instants are fractions of the exposure.
:func:`binned_note` is the one line a run on them says.

Before the loop, :func:`settle_pattern` gives a method the sensor's fixed pattern to remove
from every frame (:mod:`trmd_cli.fixed_pattern`), and :func:`settle_recording` one contrast
threshold for the whole recording (one sensor, one threshold), estimated on the frames of it
that hold the most events: steadier than an estimate per frame, and not paid for again on every
frame (:func:`settle` does both). The threshold reads frames spread over the recording, which
the loop then does not read again; the pattern reads the same frames' images alone.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from .edi import check_blurry
from .errors import InputError
from .events import Exposure
from .fixed_pattern import FixedPattern, estimate_fixed_pattern
from .methods import Estimate, Method, MethodConfig, window_model
from .read.folders import BinnedSource, BinnedWindow, FrameWindow
from .threads import map_shared
from .threshold import (
    INSTANTS,
    MIN_EVENTS,
    ContrastObjective,
    RecordingContrast,
    search_contrast_pooled,
)

__all__ = ["FrameResult", "ContrastNotes", "deblur_frames", "exposure_instants", "binned_note",
           "recording_contrast", "settle_recording", "recording_line", "recording_pattern",
           "settle_pattern", "pattern_line", "pattern_from", "candidates_of", "Settled", "settle",
           "RECORDING_FRAMES", "RECORDING_CANDIDATES"]

#: frames a recording's contrast threshold is estimated from: those with the most events
RECORDING_FRAMES = 3
#: the candidates for them (and the frames the fixed pattern is estimated from): at most this
#: many frames spread evenly over the recording
RECORDING_CANDIDATES = 16


def candidates_of(n: int, candidates: int) -> list[int]:
    """Positions of at most ``candidates`` frames spread evenly over ``n``."""
    return sorted({int(round(p)) for p in np.linspace(0, n - 1, min(n, candidates))})


@dataclass(frozen=True, eq=False)
class FrameResult:
    """One deblurred frame.

    Attributes:
        index: frame number; name: for folder names and messages.
        blurry: (H, W[, 3]) float32 [0, 1] input.
        exposure: its window (µs, time offset applied); None for binned events, which have no
            event clock (the instants are then fractions of the exposure, 0 = start, 1 = end).
        estimate: the latent frames (see :class:`~trmd_cli.methods.Estimate`).
        num_events: events in the window; binned events: Σ|count| over the frame's bins, a
            lower bound on them (a bin holds net counts).
        passthrough: the window held no events: ``estimate.frames`` repeat the blurry frame.
        warnings: messages for the user.
    """

    index: int
    name: str
    blurry: np.ndarray
    exposure: Exposure | None
    estimate: Estimate
    num_events: int
    passthrough: bool = False
    warnings: tuple[str, ...] = ()

    @property
    def frames(self) -> np.ndarray:
        return self.estimate.frames

    @property
    def instants_us(self) -> np.ndarray:
        return self.estimate.instants_us

    @property
    def binned(self) -> bool:
        """From binned events: ``instants_us`` are fractions of the exposure, not µs."""
        return self.exposure is None

    @property
    def middle_index(self) -> int:
        """Index of the frame nearest to mid-exposure."""
        mid = 0.5 if self.exposure is None else self.exposure.mid_us
        return int(np.abs(self.instants_us - mid).argmin())

    @property
    def middle(self) -> np.ndarray:
        """The frame nearest to mid-exposure."""
        return self.frames[self.middle_index]


def exposure_instants(exposure: Exposure, k: int) -> np.ndarray:
    """K instants spread evenly over the window, ends included (K = 1: the middle), µs."""
    if k < 1:
        raise InputError(f"`per_exposure` must be ≥ 1, got {k}")
    if k == 1:
        return np.array([exposure.mid_us])
    return exposure.start_us + np.arange(k) * (exposure.duration_us / (k - 1))


def deblur_frames(source: Iterable[FrameWindow | BinnedWindow], method: Method, *,
                  per_exposure: int | None = None) -> Iterator[FrameResult]:
    """Run ``method`` on every frame of ``source``.

    Args:
        per_exposure: frames per exposure; None = the method's 2N+1 at ``t0 + k·T/2N``.
            Binned events have no times to place others at: only 2N+1 (or None) is allowed.
    Yields:
        :class:`FrameResult` in the source's order. A window without events (binned: bins
        that are all zero) is passed through (the blurry frame repeated) with a warning.
    Raises:
        InputError: a binned item with ``per_exposure`` other than 2N+1.
    """
    for item in source:
        if isinstance(item, BinnedWindow):
            yield _from_bins(item, method, per_exposure)
            continue
        frame, events = item.frame, item.events
        exposure = frame.exposure
        blurry = check_blurry(frame.image, events.width, events.height, frame.name)
        blurry, notes = _in_range(blurry, frame)
        inst = exposure.instants_us(method.n) if per_exposure is None else \
            exposure_instants(exposure, per_exposure)
        inside = events.slice(exposure.start_us, exposure.end_us + 1)
        if len(inside) == 0:
            frames = np.repeat(blurry[None], len(inst), axis=0)
            yield FrameResult(frame.index, frame.name, blurry, exposure,
                              Estimate(frames, inst, None), 0, True,
                              (*notes, f"frame {frame.name}: no events in its exposure window "
                               f"[{exposure.start_us}, {exposure.end_us}] µs; passed through "
                               "unchanged"))
            continue
        est = method(blurry, events, exposure, inst)
        yield FrameResult(frame.index, frame.name, blurry, exposure, est, len(inside), False,
                          (*notes, *(f"frame {frame.name}: {note}" for note in est.notes)))


def recording_contrast(source: Sequence, *, hot_pixels: bool = True, drop_isolated: bool = True,
                       frames: int = RECORDING_FRAMES,
                       candidates: int = RECORDING_CANDIDATES,
                       share_instants: bool = True,
                       pattern: FixedPattern | None = None) -> RecordingContrast | None:
    """One contrast threshold for a recording: the consistency energy of
    :mod:`trmd_cli.threshold` pooled over the ``frames`` frames with the most events among
    ``candidates`` spread evenly over it (ties: the earlier frame), minimised as one.

    Which frames are used depends on the recording only, never on which of its frames a
    process deblurs, so every share of a split run settles the same c. Memory: ``frames + 1``
    windows at a time. Cost: reading the candidates, and the search's evaluations on
    ``frames`` frames.

    Args:
        source: the recording's items (:class:`FrameWindow` or :class:`BinnedWindow`), with
            ``len`` and ``subset(positions)``.
        hot_pixels: ignore the events of hot pixels, as the method will.
        drop_isolated: leave out the events no neighbour corroborates, as the method will
            (:mod:`trmd_cli.isolated`).
        share_instants: the frames share out the energy's instants (frame i of n takes every
            n-th from the i-th), so that an evaluation costs what one frame's does; else each
            frame is measured at all of them.
        pattern: the sensor's fixed pattern, removed from the frames as the method will (one
            not removed leaves them as they are).
    Returns:
        The estimate, or None when no candidate holds :data:`~trmd_cli.threshold.MIN_EVENTS`
        events (each frame then settles its own c, as a lone frame does).
    """
    if frames < 1 or candidates < 1:
        raise InputError(f"`frames` and `candidates` must be ≥ 1, got {frames}, {candidates}")
    n = len(source)
    if n == 0:
        return None
    positions = candidates_of(n, candidates)
    kept: list[tuple[int, int, FrameWindow | BinnedWindow]] = []
    # (the windows read here are kept for the deblurring pass, which then reads them once)
    for pos, item in zip(positions, source.subset(positions, keep=True), strict=True):
        count = _count(item)
        if count < MIN_EVENTS:
            continue
        # counting is cheap; the objectives are built for the frames kept only
        kept.append((count, -pos, item))
        kept.sort(key=lambda k: (k[0], k[1]), reverse=True)
        del kept[frames:]
    kept.sort(key=lambda k: -k[1])  # frame order, for the report
    # the frames share out the energy's instants (frame i takes every len(kept)-th from i):
    # an evaluation then costs what one frame's does, and sees as many instants
    step = len(kept) if share_instants else 1
    def objective(numbered):
        i, (_, _, item) = numbered
        return _objective(item, hot_pixels, drop_isolated, INSTANTS[i % step::step], pattern)

    # the frames' objectives (sorting, tables and filters of 10⁴–10⁵ events each) on the
    # process's threads
    objs = map_shared(objective, enumerate(kept))
    used = [(item.frame.name, obj) for (_, _, item), obj in zip(kept, objs, strict=True)
            if obj is not None]
    if not used:
        return None
    c, energy, at_bound, evaluations = search_contrast_pooled([o for _, o in used])
    return RecordingContrast(c, tuple(name for name, _ in used), energy, evaluations, at_bound)


def _count(item: FrameWindow | BinnedWindow) -> int:
    """Events in an item's exposure (binned: Σ|count|, a lower bound on them)."""
    if isinstance(item, BinnedWindow):
        bins = item.bins
        return int(np.abs(bins.astype(np.int64, copy=False)).sum()) if bins.dtype.kind in "iu" \
            else int(np.abs(bins).sum())
    exposure = item.frame.exposure
    return len(item.events.slice(exposure.start_us, exposure.end_us + 1))


def _item_blurry(item: FrameWindow | BinnedWindow) -> np.ndarray:
    """An item's blurry frame as the loop gives it to a method (:func:`_as_given`, against its
    events' size)."""
    h, w = item.bins.shape[1:] if isinstance(item, BinnedWindow) else \
        (item.events.height, item.events.width)
    return _as_given(item.frame, w, h)


def _as_given(frame, width: int, height: int) -> np.ndarray:
    """A frame's image as the loop gives it to a method: checked against the ``width`` ×
    ``height`` sensor, float32, clipped to [0, 1]."""
    return _in_range(check_blurry(frame.image, width, height, frame.name), frame)[0]


def _objective(item: FrameWindow | BinnedWindow, hot_pixels: bool, drop_isolated: bool,
               instants: np.ndarray, pattern: FixedPattern | None = None
               ) -> ContrastObjective | None:
    """The threshold's objective for one item (its frame without ``pattern``); None when, hot
    pixels left out, it holds too few events to estimate from (or none near the instants the
    energy is measured at)."""
    blurry = _item_blurry(item)
    if pattern is not None:
        blurry = pattern.removed_from(blurry)
    if isinstance(item, BinnedWindow):
        model, _, _ = window_model(item.bins, None, False, drop_isolated)
        objective = ContrastObjective.from_bins(model, blurry, instants)
    else:
        model, _, _ = window_model(item.events, item.frame.exposure, hot_pixels, drop_isolated)
        if model.count < MIN_EVENTS:
            return None
        objective = ContrastObjective.from_events(model, blurry, instants)
    return objective if objective.total > 0 else None


def recording_pattern(source: Sequence, candidates: int = RECORDING_CANDIDATES
                      ) -> FixedPattern | None:
    """The sensor's fixed pattern (:func:`~trmd_cli.fixed_pattern.estimate_fixed_pattern`)
    from at most ``candidates`` frames spread evenly over ``source`` (the frames the
    recording's threshold chooses among; their images only, no events); None for a source of
    one frame, which has no pattern to tell from its scene. Which frames are used depends on
    the recording only."""
    if len(source) < 2:
        return None
    return pattern_from(source.subset(candidates_of(len(source), candidates)).frames(),
                        source.width, source.height)


def pattern_from(frames: Iterable, width: int, height: int) -> FixedPattern:
    """:func:`~trmd_cli.fixed_pattern.estimate_fixed_pattern` on ``frames`` (each with its
    ``image``, ``name`` and ``note``, as :class:`~trmd_cli.read.base.Frame`), each checked
    against the ``width`` × ``height`` sensor and clipped as the loop hands it to a method."""
    images, names = [], []
    for frame in frames:
        images.append(_as_given(frame, width, height))
        names.append(frame.name)
    return estimate_fixed_pattern(images, names)


def settle_pattern(method: Method, source: Sequence, config: MethodConfig
                   ) -> tuple[Method, FixedPattern | None]:
    """``method`` removing the recording's fixed pattern from every frame when ``config``
    asks for it (``fixed_pattern``) and the recording shows one; else ``method`` unchanged.
    Also gives the estimate, removed or not (None: not asked for, or a source of one frame)."""
    pattern = recording_pattern(source) if config.fixed_pattern else None
    return (method if pattern is None else method.for_pattern(pattern)), pattern


def pattern_line(pattern: FixedPattern) -> str:
    """What a run says about the sensor's fixed pattern."""
    if pattern.removed:
        return (f"removed the sensor's fixed pattern (RMS {pattern.rms * 255:.1f} grey levels "
                f"of 255), estimated from {len(pattern.frames)} frames (`fixed_pattern=False` "
                "keeps it)")
    return f"no fixed pattern removed: {pattern.reason}"


def settle_recording(method: Method, source: Sequence, config: MethodConfig,
                     pattern: FixedPattern | None = None
                     ) -> tuple[Method, RecordingContrast | None]:
    """``method`` with one estimated c for the whole recording ``source`` when ``config``
    asks for it (c not given, ``contrast_scope="recording"``) and the method uses c; else
    ``method`` unchanged. Also gives the estimate (None: not made, or no frame held enough
    events — every frame then settles its own c; a source of one frame settles its own).
    ``pattern``: the fixed pattern the method removes (:func:`settle_pattern`), removed from
    the frames the threshold is measured on too."""
    if config.contrast is not None or config.contrast_scope != "recording" \
            or not method.needs.contrast or len(source) < 2:
        # (one frame: its own estimate is the recording's)
        return method, None
    rec = recording_contrast(source, hot_pixels=config.hot_pixels,
                             drop_isolated=config.drop_isolated, pattern=pattern)
    return (method, None) if rec is None else (method.for_recording(rec), rec)


@dataclass(frozen=True, eq=False)
class Settled:
    """What a run settles once for a recording before its frames (every process of a split
    run gets the same).

    Attributes:
        contrast: its one estimated c (None: not estimated over the recording).
        pattern: its sensor's fixed pattern, removed or with the reason it is not (None: not
            asked for, or one frame).
    """

    contrast: RecordingContrast | None = None
    pattern: FixedPattern | None = None

    def applied_to(self, method: Method) -> Method:
        """``method`` with what was settled: the pattern removed, the recording's c."""
        if self.pattern is not None:
            method = method.for_pattern(self.pattern)
        return method if self.contrast is None else method.for_recording(self.contrast)

    def lines(self) -> list[str]:
        """What a run says about them."""
        return ([] if self.pattern is None else [pattern_line(self.pattern)]) + \
            ([] if self.contrast is None else [recording_line(self.contrast)])


def settle(method: Method, source: Sequence, config: MethodConfig) -> tuple[Method, Settled]:
    """:func:`settle_pattern`, then :func:`settle_recording` on the frames without the
    pattern: the method to run over ``source`` and what was settled."""
    method, pattern = settle_pattern(method, source, config)
    method, rec = settle_recording(method, source, config, pattern)
    return method, Settled(rec, pattern)


def recording_line(rec: RecordingContrast) -> str:
    """What a run says about its recording's threshold."""
    from .threshold import CONTRAST_BOUNDS

    shown = ", ".join(rec.frames)
    line = (f"contrast threshold c = {rec.contrast:.3f}, estimated once for the recording from "
            f"frame{'s' if len(rec.frames) > 1 else ''} {shown}")
    if rec.at_bound:
        lo, hi = CONTRAST_BOUNDS
        line += (f" (at the edge of the search range {lo:g}–{hi:g}: the sensor's threshold "
                 "may lie beyond it; set `contrast` if you know it)")
    return line


def _in_range(blurry: np.ndarray, frame) -> tuple[np.ndarray, tuple[str, ...]]:
    """The frame with values outside [0, 1] clipped, and what was said about it: a frame of
    −1e30 (or of 0–255 stored as floats read as they are) must not deblur without a word."""
    from .read.frames import clip_note

    notes = () if getattr(frame, "note", None) is None else (frame.note,)
    note = clip_note(blurry, frame.name)
    if note is None:
        return blurry, notes
    return np.clip(blurry, 0.0, 1.0), (*notes, note)


def _from_bins(item: BinnedWindow, method: Method, per_exposure: int | None) -> FrameResult:
    """One binned frame through ``method.from_bins`` at its 2N+1 instants k/2N."""
    frame, bins = item.frame, item.bins
    k = 2 * method.n + 1
    if per_exposure is not None and per_exposure != k:
        raise InputError(f"binned events have no event times to place "
                         f"`per_exposure={per_exposure}` frames at",
                         hint=f"leave out `per_exposure`: binned events give the 2N+1 = {k} "
                              "frames at the instants k/2N")
    blurry = check_blurry(frame.image, bins.shape[2], bins.shape[1], frame.name)
    blurry, notes = _in_range(blurry, frame)
    count = _count(item)
    if count == 0:
        fractions = np.linspace(0.0, 1.0, k)
        frames = np.repeat(blurry[None], k, axis=0)
        return FrameResult(frame.index, frame.name, blurry, None,
                           Estimate(frames, fractions, None), 0, True,
                           (*notes, f"frame {frame.name}: its bins hold no events; passed "
                            "through unchanged"))
    est = method.from_bins(blurry, bins)
    return FrameResult(frame.index, frame.name, blurry, None, est, count, False, notes)


def binned_note(source: BinnedSource, method: Method, *, stream: bool = False) -> str:
    """The one line a run on binned events says: what the data lacks and what that costs.

    Args:
        source: the binned frames. method: the method that runs on them.
        stream: for a continuous stream (``trmd hfr``): say that there is no gap filling.
    """
    b, two_n = source.bins_per_frame, 2 * method.n
    parts = [f"{source.path.name}: binned events ({b} bins per frame, no event times): the "
             f"{two_n + 1} frames sit at fractions k/{two_n} of each exposure"]
    if b % two_n:
        parts.append(f"{b} bins do not split into {two_n} equal parts, so the bins that "
                     "straddle an instant are taken as their events spread evenly")
    if method.needs.timing:
        parts.append("the network's timing inputs get the counts")
    parts.append("hot pixels are not masked (the bins hold no per-event information)")
    if stream:
        parts.append("the exposures' frames only, in order: in-between frames and gap "
                     "filling need event times")
    return "; ".join(parts)


class ContrastNotes:
    """What the frames of a run said about their contrast threshold, told once: one line per
    kind of note with the number of frames it concerns, not one line per frame (a recording of
    hundreds of dark frames would otherwise print hundreds of lines).

    Usage: ``notes.add(result)`` for every :class:`FrameResult`, then ``notes.lines()``.
    """

    def __init__(self) -> None:
        self.frames = 0
        self._fallback: list[tuple[str, str]] = []
        self._edge: list[tuple[str, str]] = []

    def add(self, result: FrameResult) -> None:
        est = result.estimate
        self.add_note(result.name, est.contrast_note, est.contrast_reliable)

    def add_note(self, name: str, note: str | None, reliable: bool) -> None:
        """One frame's note (None: it said nothing), for frames deblurred elsewhere (another
        process) whose :class:`FrameResult` is not here."""
        self.frames += 1
        if note is None:
            return
        kind = self._fallback if not reliable else self._edge
        kind.append((name, note))

    def lines(self) -> list[str]:
        out = []
        for notes in (self._fallback, self._edge):
            if not notes:
                continue
            name, note = notes[0]
            if len(notes) == 1:
                where = f"frame {name}"
            else:
                where = f"{len(notes)} of {self.frames} frames (the first, {name})"
            out.append(f"{where}: {note} — set `contrast` if you know it")
        return out
