"""High frame rate: one continuous, evenly timed frame stream from consecutive exposures.

Each exposure contributes its latent frames (:func:`trmd_cli.deblur.deblur_frames`); the gap
before the next exposure is filled at the same time step from the events in it. Binned events
have no event times: their stream is the exposures' frames in order, each at its fraction of
its exposure, with no gap filling.

A gap needs only the :class:`Edge` of the exposure on either side of it (its end frames,
instants and c), so the stream can also be made in pieces — each exposure's frames
(:func:`exposure_frames`), each gap's (:func:`gap_frames`) — by different processes
(:mod:`trmd_cli.hfr_batch`), with the same frames as :func:`hfr_stream`.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .deblur import FrameResult
from .edi import propagate
from .errors import InputError
from .events import Exposure

#: what a run says when some gap got fewer frames than real time would need
CAPPED_NOTE = ("some gaps between exposures are long: they were filled with fewer frames than "
               "real time would need (raise `max_gap_frames`)")

__all__ = ["CAPPED_NOTE", "HfrFrame", "Edge", "hfr_stream", "exposure_frames", "gap_frames",
           "timestamp_row", "check_time_order", "ExposureContrast", "contrast_meta"]


def check_time_order(exposures: Sequence[Exposure], path: str | Path | None = None) -> None:
    """A stream needs its exposures in time order, one after the other (µs): its frames run
    from each exposure's start to its end, so an overlap would turn its time back.

    Raises:
        InputError: an exposure starts before the one listed ahead of it, or before that one
            ends.
    """
    for k in range(1, len(exposures)):
        a, b = exposures[k - 1], exposures[k]
        if b.start_us < a.start_us:
            raise InputError("the frames are not in time order", path=path,
                             hint="name the frames so that their numbers follow time")
        if b.start_us < a.end_us:
            raise InputError(f"exposure windows #{k - 1} [{a.start_us}, {a.end_us}] µs and "
                             f"#{k} [{b.start_us}, {b.end_us}] µs overlap: the video's time "
                             "would run backwards", path=path,
                             hint="check the exposure windows stored with the events; hfr "
                                  "plays exposures one after the other (deblur takes "
                                  "overlapping ones)")


@dataclass(frozen=True)
class ExposureContrast:
    """One exposure's c in a stream, as meta.json and the run's line tell it.

    Attributes:
        frame: its frame's name. contrast: its c, or None (passed through, no events).
        default: c is the default, its window holding too few events to estimate it from.
    """

    frame: str
    contrast: float | None
    default: bool = False

    @classmethod
    def of(cls, result) -> ExposureContrast:
        """A :class:`~trmd_cli.deblur.FrameResult`'s."""
        c = result.estimate.contrast
        return cls(result.name, None if c is None else float(c),
                   result.estimate.contrast_default)


def contrast_meta(records: Sequence[ExposureContrast]) -> dict:
    """meta.json's entries for the exposures' c: one per exposure in stream order (null where
    it was passed through), their frames, and those that took the default."""
    return {"contrast": [r.contrast for r in records],
            "contrast_frames": [r.frame for r in records],
            "contrast_defaults": [r.frame for r in records if r.default]}


@dataclass(frozen=True, eq=False)
class HfrFrame:
    """One frame of the continuous stream: time, image, and where it came from.

    Attributes:
        t_us: the time, µs on the events' clock; None for binned events (no event clock).
        image: (H, W[, 3]) float32 [0, 1] intensity, not clipped.
        kind: ``"exposure"`` or ``"gap"``.
        source: the frame (or the two frames around a gap) it came from.
        fraction: binned events: the instant as a fraction of its exposure (0 = start,
            1 = end); None otherwise.
        stamp: ``t_us`` as timestamps.txt writes it, computed from whole numbers (a float64
            near an epoch clock's 1.5e15 µs resolves only a quarter of a microsecond); None:
            from ``t_us``.
    """

    t_us: float | None
    image: np.ndarray
    kind: str  # "exposure" or "gap"
    source: str
    fraction: float | None = None
    stamp: str | None = None


def timestamp_row(frame: HfrFrame) -> str:
    """A frame's line in timestamps.txt after its file name: its time (µs, 3 decimals; binned
    events: its fraction of the exposure), kind and source."""
    from .write import fmt_fraction

    when = fmt_fraction(frame.fraction) if frame.t_us is None else \
        frame.stamp if frame.stamp is not None else f"{frame.t_us:.3f}"
    return f"{when} {frame.kind} {frame.source}"


@dataclass(frozen=True, eq=False)
class Edge:
    """What filling the gap beside an exposure needs of it.

    Attributes:
        name: its frame's name. first, last: (H, W[, 3]) float32 latent frames at its first and
            last instants. first_us, last_us: those instants, µs. count: its frames in the
            stream (its time step is ``duration_us / (count − 1)``). duration_us: its exposure,
            µs. contrast: its c, or None (passed through, or a method that settled none).
    """

    name: str
    first: np.ndarray
    last: np.ndarray
    first_us: float
    last_us: float
    count: int
    duration_us: int
    contrast: float | None

    @classmethod
    def of(cls, res: FrameResult) -> Edge:
        """The edge of a deblurred exposure (not binned: binned results have no times)."""
        return cls(res.name, res.frames[0], res.frames[-1], float(res.instants_us[0]),
                   float(res.instants_us[-1]), len(res.instants_us), res.exposure.duration_us,
                   res.estimate.contrast)


def exposure_frames(res: FrameResult) -> Iterator[HfrFrame]:
    """An exposure's own frames of the stream, in time order."""
    if res.binned:
        for f, img in zip(res.instants_us, res.frames, strict=True):
            yield HfrFrame(None, img, "exposure", res.name, float(f))
        return
    from .write import instant_texts

    for t, img, stamp in zip(res.instants_us, res.frames,
                             instant_texts(res.exposure, len(res.instants_us)), strict=True):
        yield HfrFrame(float(t), img, "exposure", res.name, stamp=stamp)


def gap_frames(a: Edge, b: Edge, recording=None, *, max_gap_frames: int | None = None,
               contrast: float | None = None) -> tuple[list[HfrFrame], bool]:
    """The frames filling the gap between consecutive exposures ``a`` and ``b`` (see
    :func:`hfr_stream`), and whether there were fewer than real time needs (the gap is longer
    than ``max_gap_frames`` steps)."""
    frames = list(_gap_frames(a, b, recording, max_gap_frames, contrast))
    capped = bool(frames) and frames[0] is None
    return (frames[1:] if capped else frames), capped


def hfr_stream(results: Iterable[FrameResult], recording=None, *, fill_gaps: bool = True,
               max_gap_frames: int | None = None, contrast: float | None = None,
               notes: list[str] | None = None) -> Iterator[HfrFrame]:
    """One evenly timed frame stream from consecutive exposures.

    Each exposure contributes its frames; the gap before the next exposure is filled at the
    same time step (the spacing of the exposure's own frames): forward from the exposure's last
    frame and backward from the next one's first frame, both by event integration
    (:func:`trmd_cli.edi.propagate`), cross-faded over the gap so the stream is continuous.
    Without events in the gap (files holding only each exposure's events) this is a plain
    cross-fade.

    Args:
        results: from :func:`trmd_cli.deblur.deblur_frames`, in time order.
        recording: where the gaps' events come from (None: no events, cross-fade only).
        fill_gaps: False = exposures only (always so for binned results: no event times).
        max_gap_frames: most frames per gap (None: 4 × frames per exposure); longer gaps get a
            coarser step and a note.
        contrast: c for the gaps when a result has none (TRMD without in-between frames).
        notes: list that receives one-time remarks for the user.
    """
    prev: Edge | None = None
    capped = False
    for res in results:
        if res.binned:
            yield from exposure_frames(res)
            prev = None
            continue
        edge = Edge.of(res)
        if prev is not None and fill_gaps:
            gap, short = gap_frames(prev, edge, recording, max_gap_frames=max_gap_frames,
                                    contrast=contrast)
            capped = capped or short
            yield from gap
        yield from exposure_frames(res)
        prev = edge
    if capped and notes is not None:
        notes.append(CAPPED_NOTE)


def _gap_frames(a: Edge, b: Edge, recording, max_frames: int | None,
                contrast: float | None):
    t0, t1 = a.last_us, b.first_us
    if t1 <= t0:
        return
    k = a.count
    step = (a.duration_us / (k - 1)) if k > 1 else float(a.duration_us)
    count = int(np.floor((t1 - t0) / step - 0.5))
    if count < 1:
        return
    cap = max_frames if max_frames is not None else 4 * max(k, 1)
    if count > cap:
        count = cap
        yield None  # tells the caller the gap was compressed
    times = t0 + (np.arange(1, count + 1)) * ((t1 - t0) / (count + 1))
    fa, fb = a.last, b.first
    ca = a.contrast or b.contrast or contrast
    cb = b.contrast or a.contrast or contrast
    ev = None
    if recording is not None and ca and cb:
        ev = recording.events(t0, t1 + 1)
        if len(ev) == 0:
            ev = None
    if ev is not None:
        fwd = propagate(fa, ev, t0, times, ca)
        bwd = propagate(fb, ev, t1, times, cb)
    else:
        fwd = np.repeat(fa[None], count, axis=0)
        bwd = np.repeat(fb[None], count, axis=0)
    w = ((times - t0) / (t1 - t0)).astype(np.float32)
    w = w.reshape(-1, *([1] * (fwd.ndim - 1)))
    mix = (1 - w) * fwd + w * bwd
    from .write import exact_us_text

    # the edges' instants are whole µs where they are an exposure's ends (one frame per
    # exposure: its middle, which may fall between two)
    exact = float(t0).is_integer() and float(t1).is_integer()
    for i, (t, img) in enumerate(zip(times, mix, strict=True), 1):
        stamp = exact_us_text(int(t0), i * int(t1 - t0), count + 1) if exact else None
        yield HfrFrame(float(t), img, "gap", f"{a.name}-{b.name}", stamp=stamp)
