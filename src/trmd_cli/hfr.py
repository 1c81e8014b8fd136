"""High frame rate: one continuous, evenly timed frame stream from consecutive exposures.

Each exposure contributes its latent frames (:func:`trmd_cli.deblur.deblur_frames`); the gap
before the next exposure is filled at the same time step from the events in it. Binned events
have no event times: their stream is the exposures' frames in order, each at its fraction of
its exposure, with no gap filling.
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

__all__ = ["HfrFrame", "hfr_stream", "check_time_order"]


def check_time_order(exposures: Sequence[Exposure], path: str | Path | None = None) -> None:
    """A stream needs its exposures in time order (by start, µs).

    Raises:
        InputError: an exposure starts before the one listed ahead of it.
    """
    starts = [e.start_us for e in exposures]
    if any(b < a for a, b in zip(starts, starts[1:])):  # noqa: B905 - offset pairs
        raise InputError("the frames are not in time order", path=path,
                         hint="name the frames so that their numbers follow time")


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
    """

    t_us: float | None
    image: np.ndarray
    kind: str  # "exposure" or "gap"
    source: str
    fraction: float | None = None


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
    prev: FrameResult | None = None
    capped = False
    for res in results:
        if res.binned:
            for f, img in zip(res.instants_us, res.frames, strict=True):
                yield HfrFrame(None, img, "exposure", res.name, float(f))
            prev = None
            continue
        if prev is not None and fill_gaps:
            gap = list(_gap_frames(prev, res, recording, max_gap_frames, contrast))
            if gap and gap[0] is None:
                capped = True
                gap = gap[1:]
            yield from gap
        for t, img in zip(res.instants_us, res.frames, strict=True):
            yield HfrFrame(float(t), img, "exposure", res.name)
        prev = res
    if capped and notes is not None:
        notes.append("some gaps between exposures are long: they were filled with fewer "
                     "frames than real time would need (raise `max_gap_frames`)")


def _gap_frames(a: FrameResult, b: FrameResult, recording, max_frames: int | None,
                contrast: float | None):
    t0, t1 = float(a.instants_us[-1]), float(b.instants_us[0])
    if t1 <= t0:
        return
    k = len(a.instants_us)
    step = (a.exposure.duration_us / (k - 1)) if k > 1 else float(a.exposure.duration_us)
    count = int(np.floor((t1 - t0) / step - 0.5))
    if count < 1:
        return
    cap = max_frames if max_frames is not None else 4 * max(k, 1)
    if count > cap:
        count = cap
        yield None  # tells the caller the gap was compressed
    times = t0 + (np.arange(1, count + 1)) * ((t1 - t0) / (count + 1))
    fa, fb = a.frames[-1], b.frames[0]
    ca = a.estimate.contrast or b.estimate.contrast or contrast
    cb = b.estimate.contrast or a.estimate.contrast or contrast
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
    for t, img in zip(times, mix, strict=True):
        yield HfrFrame(float(t), img, "gap", f"{a.name}-{b.name}")
