"""Compose the stages: read → window → voxelize / estimate → reconstruct, one frame at a time.

Never prints: warnings travel with the results (``FrameResult.warnings``) and in
:attr:`Inputs.warnings`; the CLI says them. Two entry points:

* :func:`open_inputs` turns the command line's positional inputs into a
  :class:`~trmd_cli.read.folders.FrameSource` (frames + exposure windows + events per window);
* :func:`deblur_frames` runs a :class:`Method` over it and yields :class:`FrameResult` items;
  :func:`hfr_stream` turns those into one continuous, evenly timed frame stream (the gaps
  between exposures filled from the events).

Methods are small callables (``EdiMethod``, ``TrmdMethod``) chosen by :func:`make_method`;
:data:`DEFAULT_METHOD` is the one constant to flip when TRMD weights ship.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol

import numpy as np

from .edi import EdiEvents, check_blurry, hot_pixel_mask, propagate
from .errors import InputError
from .events import EventStream, Exposure
from .precision import PRECISIONS
from .read.base import ReadOptions
from .read.folders import FrameEntry, FrameSource, FrameWindow
from .threshold import search_contrast

__all__ = [
    "DEFAULT_METHOD",
    "METHODS",
    "MethodConfig",
    "Estimate",
    "Method",
    "EdiMethod",
    "TrmdMethod",
    "make_method",
    "Inputs",
    "open_inputs",
    "FrameResult",
    "deblur_frames",
    "exposure_instants",
    "HfrFrame",
    "hfr_stream",
    "write_result_folder",
    "clipped_fraction",
]

#: the method used when none is asked for; flip to "trmd" once weights ship
DEFAULT_METHOD = "trmd"
METHODS = ("edi", "trmd")
#: N used by EDI when none is given (2N+1 = 7 frames)
DEFAULT_N = 3


# --------------------------------------------------------------------------------------------
# methods


@dataclass(frozen=True)
class MethodConfig:
    """How to deblur.

    Attributes:
        method: ``"edi"`` or ``"trmd"``.
        n: 2N+1 latent frames; None = 3 for EDI, the weights' N for TRMD.
        contrast: EDI's contrast threshold c; None = estimate it per frame. TRMD uses it as an
            input when its weights take one (``prior="edi_c"``, as the shipped default) and to
            place frames at instants between its own (event integration).
        hot_pixels: ignore the events of hot pixels (see :func:`trmd_cli.edi.hot_pixel_mask`).
        weights, device, threads, precision: TRMD only (see ``TrmdEstimator.load``;
            ``precision="auto"`` runs the network in bfloat16 on CPUs that compute it natively
            — on the pinned validation set within 0.003 dB of float32).
    """

    method: str = DEFAULT_METHOD
    n: int | None = None
    contrast: float | None = None
    hot_pixels: bool = True
    weights: str | Path | None = None
    device: str = "auto"
    threads: int | None = None
    precision: str = "auto"

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise InputError(f"unknown method {self.method!r}", hint="use --method edi or trmd")
        if self.n is not None and self.n < 1:
            raise InputError(f"N must be ≥ 1, got {self.n}", hint="use --n 3 (7 latent frames)")
        if self.contrast is not None and not (np.isfinite(self.contrast) and self.contrast > 0):
            raise InputError(f"--contrast must be a positive number or 'auto', got "
                             f"{self.contrast}")
        if self.precision not in PRECISIONS:
            raise InputError(f"unknown precision {self.precision!r}",
                             hint="use --precision " + ", ".join(PRECISIONS))


@dataclass(frozen=True, eq=False)
class Estimate:
    """Latent frames of one exposure.

    Attributes:
        frames: (K, H, W[, 3]) float32, not clipped.
        instants_us: (K,) float64 µs, the time of each frame.
        contrast: c used (EDI; TRMD's input or its in-between frames); None if none was needed.
        contrast_estimated: c came from :func:`trmd_cli.threshold.search_contrast`.
        contrast_reliable: False when too few events to estimate (a default was used).
        hot_pixels: number of pixels whose events were ignored.
    """

    frames: np.ndarray
    instants_us: np.ndarray
    contrast: float | None
    contrast_estimated: bool = False
    contrast_reliable: bool = True
    hot_pixels: int = 0


class Method(Protocol):
    """An estimator: blurry frame + its events → latent frames at given instants."""

    name: str
    n: int
    weights_hash: str | None
    precision: str | None  # the network's arithmetic as run; None for weight-free methods

    def __call__(self, blurry: np.ndarray, events: EventStream, exposure: Exposure,
                 instants_us: np.ndarray | None = None) -> Estimate: ...


class EdiMethod:
    """EDI with a given or per-frame estimated contrast threshold."""

    name = "edi"
    weights_hash = None
    precision = None

    def __init__(self, n: int = DEFAULT_N, contrast: float | None = None,
                 hot_pixels: bool = True) -> None:
        self.n = n
        self.contrast = contrast
        self.hot_pixels = hot_pixels

    def prepare(self, blurry: np.ndarray, events: EventStream, exposure: Exposure
                ) -> tuple[EdiEvents, float, bool, bool, np.ndarray | None]:
        """Sort the window's events and settle c: (prep, c, estimated, reliable, hot mask)."""
        hot = hot_pixel_mask(events, exposure) if self.hot_pixels else None
        prep = EdiEvents.build(events, exposure, hot)
        if self.contrast is not None:
            return prep, self.contrast, False, True, hot
        est = search_contrast(blurry, prep)
        return prep, est.contrast, True, est.reliable, hot

    def __call__(self, blurry, events, exposure, instants_us=None) -> Estimate:
        b = check_blurry(blurry, events.width, events.height)
        inst = exposure.instants_us(self.n) if instants_us is None else \
            np.asarray(instants_us, np.float64)
        prep, c, estimated, reliable, hot = self.prepare(b, events, exposure)
        fr = (inst - exposure.start_us) / exposure.duration_us
        return Estimate(prep.latent(b, fr, c), inst, c, estimated, reliable,
                        0 if hot is None else int(hot.sum()))


class TrmdMethod:
    """TRMD (RE-Net residuals + reconstruction). Weights that take the threshold c get it given
    or estimated as EDI's; instants other than the 2N+1 are propagated from the nearest
    reconstructed frame by event integration (with the same c)."""

    name = "trmd"

    def __init__(self, n: int | None = None, weights: str | Path | None = None,
                 device: str = "auto", threads: int | None = None,
                 contrast: float | None = None, hot_pixels: bool = True,
                 precision: str = "auto") -> None:
        from .models.estimator import TrmdEstimator

        self.model = TrmdEstimator.load(weights, device=device, threads=threads, expect_n=n,
                                        precision=precision)
        self.n = self.model.n
        self.weights_hash = self.model.weights_hash
        #: the network's arithmetic as run: "fp32", "bf16" or "fp16" (mixed precision)
        self.precision = self.model.precision
        self._edi = EdiMethod(self.n, contrast, hot_pixels)
        #: settle c even when no in-between instant needs it (hfr fills gaps with it)
        self.always_contrast = False

    def __call__(self, blurry, events, exposure, instants_us=None) -> Estimate:
        from .voxel import scer_levels, scer_voxels

        b = check_blurry(blurry, events.width, events.height)
        grid = exposure.instants_us(self.n)
        inst = grid if instants_us is None else np.asarray(instants_us, np.float64)
        nearest = np.abs(inst[:, None] - grid[None]).argmin(axis=1)
        exact = np.isclose(inst, grid[nearest], atol=0.5)
        # c is settled first when the network takes it, or in-between instants need it
        settle = self.model.needs_contrast or not exact.all() or self.always_contrast
        c, estimated, reliable, hot = None, False, True, None
        if settle:
            _, c, estimated, reliable, hot = self._edi.prepare(b, events, exposure)
        levels = scer_levels(events, exposure, self.n) if self.model.needs_timing else None
        frames = self.model(b, scer_voxels(events, exposure, self.n), c, levels)
        if not settle:
            return Estimate(frames[nearest], inst, None)
        n_hot = 0 if hot is None else int(hot.sum())
        if exact.all():
            return Estimate(frames[nearest], inst, c, estimated, reliable, n_hot)
        out = np.empty((len(inst), *frames.shape[1:]), np.float32)
        for k in np.unique(nearest):
            sel = nearest == k
            out[sel] = propagate(frames[k], events, grid[k], inst[sel], c, hot)
        return Estimate(out, inst, c, estimated, reliable, n_hot)


def make_method(config: MethodConfig) -> Method:
    """The estimator for ``config.method`` (loads TRMD weights once)."""
    if config.method == "trmd":
        return TrmdMethod(config.n, config.weights, config.device, config.threads,
                          config.contrast, config.hot_pixels, config.precision)
    return EdiMethod(config.n or DEFAULT_N, config.contrast, config.hot_pixels)


# --------------------------------------------------------------------------------------------
# inputs


@dataclass(eq=False)
class Inputs:
    """Frames to deblur with their windows and events.

    Attributes:
        source: the frames, one :class:`FrameWindow` at a time.
        single: one blurry image given directly (outputs go flat into OUT/, not per frame).
        paths: the input files, for meta.json.
        warnings: things the user should hear (printed by the CLI).
    """

    source: FrameSource
    single: bool
    paths: list[str]
    warnings: list[str] = field(default_factory=list)

    def close(self) -> None:
        self.source.close()

    def __post_init__(self) -> None:
        # the same file may be opened twice (window, then frames): say each warning once
        self.warnings = list(dict.fromkeys(self.warnings))

    def __enter__(self) -> Inputs:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_inputs(inputs: Sequence[str | Path], options: ReadOptions | None = None, *,
                exposure: Sequence[float] | None = None, offset_us: int = 0) -> Inputs:
    """Understand the positional inputs of ``trmd deblur`` / ``trmd hfr``.

    * ``RECORDING`` (AEDAT4, HDF5 with frames): every stored frame, its own exposure;
    * ``BLURRY EVENTS``: one image and an event file (or a folder of per-frame event files);
      the window is ``exposure`` (file's unit), else the one stored, else the events' span;
    * ``IMAGES_DIR EVENTS``: a frames folder with an event file (+ Exposure_start/end.txt) or a
      folder of per-frame event files paired by number;
    * ``BLURRY1 BLURRY2 … EVENTS``: several images, one event file storing one window each.

    ``offset_us`` (``--time-offset``) moves every exposure window relative to the events.

    Raises:
        InputError: missing files, a window outside the events' time range, image size not
            matching the sensor, counts that disagree. FormatError: unreadable files.
    """
    from .read import open_events
    from .read.folders import frames_from_recording, open_frame_folder
    from .read.frames import IMAGE_EXTENSIONS
    from .window import check_in_range, resolve_windows

    options = options or ReadOptions()
    paths = [Path(p) for p in inputs]
    if not paths:
        raise InputError("no input given", hint="trmd deblur BLURRY EVENTS -o OUT/")
    for p in paths:
        if not p.exists():
            raise InputError("not found", path=p, hint="check the path")
    names = [str(p) for p in paths]
    is_image = [p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS for p in paths]

    if len(paths) == 1:
        if is_image[0]:
            raise InputError("got a blurry image but no events", path=paths[0],
                             hint="trmd deblur BLURRY EVENTS -o OUT/")
        if paths[0].is_dir():
            raise InputError("got a frames folder but no events", path=paths[0],
                             hint="trmd deblur IMAGES_DIR EVENTS -o OUT/")
        if exposure is not None:
            raise InputError("--exposure applies to one blurry image given with its events",
                             hint="a recording's frames carry their own exposure windows")
        rec = open_events(paths[0], options)
        try:
            src = frames_from_recording(rec)
            src = FrameSource(_shift(src.entries, offset_us), src.width, src.height,
                              recording=rec, stored_frames=True, options=options,
                              warnings=list(src.warnings), owns_recording=True)
            _check_windows(src.exposures(), rec, paths[0])
        except BaseException:
            rec.close()
            raise
        return Inputs(src, False, names, list(src.warnings))

    if len(paths) == 2 and is_image[0]:
        image, events = paths
        warnings: list[str] = []
        if events.is_dir():
            src = open_frame_folder(image, events, options)
            if exposure is not None or offset_us:
                wins = src.exposures()
                src.close()
                if exposure is not None:
                    from .window import exposure_from_user

                    wins = [exposure_from_user(exposure[0], exposure[1], options.time_unit)]
                src = open_frame_folder(image, events, options,
                                        exposures=_shift_windows(wins, offset_us))
            return Inputs(src, True, names, list(src.warnings))
        with open_events(events, options) as rec:
            plan = resolve_windows(rec, exposure, options.time_unit, offset_us=offset_us)
            warnings.extend(rec.warnings)
            warnings.extend(plan.warnings)
            if len(plan.windows) != 1:
                raise InputError(
                    f"the event file stores {len(plan.windows)} exposure windows; which one "
                    "belongs to this image?", path=events,
                    hint="pass --exposure T0 T1, or give the frames folder / the recording")
            check_in_range(plan.windows[0], rec.time_range_us(), "exposure window", events)
        src = open_frame_folder(image, events, options, exposures=plan.windows)
        return Inputs(src, True, names, warnings + list(src.warnings))

    if len(paths) == 2 and paths[0].is_dir():
        if exposure is not None:
            raise InputError("--exposure applies to one blurry image, not a frames folder",
                             hint="put Exposure_start.txt / Exposure_end.txt beside the frames")
        src = open_frame_folder(paths[0], paths[1], options)
        if offset_us:
            wins = src.exposures()
            src.close()
            src = open_frame_folder(paths[0], paths[1], options,
                                    exposures=_shift_windows(wins, offset_us))
        if src.recording is not None:
            _check_windows(src.exposures(), src.recording, paths[1])
        return Inputs(src, False, names, list(src.warnings))

    if len(paths) >= 2 and all(is_image[:-1]):
        images, events = paths[:-1], paths[-1]
        if exposure is not None and len(images) > 1:
            raise InputError("--exposure applies to one blurry image",
                             hint="store one window per frame in the event file")
        rec = open_events(events, options)
        try:
            if exposure is not None:
                plan = resolve_windows(rec, exposure, options.time_unit, offset_us=offset_us)
                wins = plan.windows
            else:
                wins = _shift_windows(rec.stored_windows() or rec.frame_exposures(), offset_us)
            if len(wins) != len(images):
                raise InputError(f"{len(images)} images but the event file stores "
                                 f"{len(wins)} exposure window(s)", path=events,
                                 hint="give a frames folder with Exposure_start.txt / "
                                 "Exposure_end.txt, or one image with --exposure T0 T1")
            _check_windows(wins, rec, events)
            from .read.folders import frame_number
            from .read.frames import check_frame_matches, read_image

            check_frame_matches(read_image(images[0]), rec.width, rec.height, images[0])
            entries = [FrameEntry(frame_number(p) if frame_number(p) is not None else i,
                                  p.stem, w, p)
                       for i, (p, w) in enumerate(zip(images, wins, strict=True))]
            src = FrameSource(entries, rec.width, rec.height, recording=rec, options=options,
                              warnings=list(rec.warnings), owns_recording=True)
        except BaseException:
            rec.close()
            raise
        return Inputs(src, len(images) == 1, names, list(src.warnings))

    raise InputError("cannot tell what these inputs are: " + " ".join(names),
                     hint="give RECORDING, or BLURRY EVENTS, or IMAGES_DIR EVENTS")


def _shift_windows(windows: Iterable[Exposure], offset_us: int) -> list[Exposure]:
    return [w.shifted(offset_us) if offset_us else w for w in windows]


def _shift(entries: Iterable[FrameEntry], offset_us: int) -> list[FrameEntry]:
    return [replace(e, exposure=e.exposure.shifted(offset_us)) if offset_us else e
            for e in entries]


def _check_windows(windows: Sequence[Exposure], recording, path) -> None:
    """Bad input if the recording holds no events, or *every* window misses them (a few may:
    they pass through)."""
    from .window import check_in_range

    if not windows:
        return
    if recording.num_events() == 0:
        # else the line would blame the windows, against a time range of [0, 0]
        raise InputError("the recording holds no events", path=path,
                         hint="check the file (trmd info)")
    trange = recording.time_range_us()
    first, last = trange
    if all(w.end_us < first or w.start_us > last for w in windows):
        check_in_range(windows[0], trange, "exposure window", path)


# --------------------------------------------------------------------------------------------
# deblurring


@dataclass(frozen=True, eq=False)
class FrameResult:
    """One deblurred frame.

    Attributes:
        index: frame number; name: for folder names and messages.
        blurry: (H, W[, 3]) float32 input.
        exposure: its window (µs, time offset applied).
        estimate: the latent frames (see :class:`Estimate`).
        num_events: events in the window.
        passthrough: the window held no events: ``estimate.frames`` repeat the blurry frame.
        warnings: messages for the user.
    """

    index: int
    name: str
    blurry: np.ndarray
    exposure: Exposure
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
    def middle(self) -> np.ndarray:
        """The frame nearest to mid-exposure."""
        k = int(np.abs(self.instants_us - self.exposure.mid_us).argmin())
        return self.frames[k]


def exposure_instants(exposure: Exposure, k: int) -> np.ndarray:
    """K instants spread evenly over the window, ends included (K = 1: the middle), µs."""
    if k < 1:
        raise InputError(f"--per-exposure must be ≥ 1, got {k}")
    if k == 1:
        return np.array([exposure.mid_us])
    return exposure.start_us + np.arange(k) * (exposure.duration_us / (k - 1))


def deblur_frames(source: Iterable[FrameWindow], method: Method, *,
                  per_exposure: int | None = None) -> Iterator[FrameResult]:
    """Run ``method`` on every frame of ``source``.

    Args:
        per_exposure: frames per exposure; None = the method's 2N+1 at ``t0 + k·T/2N``.
    Yields:
        :class:`FrameResult` in the source's order. A window without events is passed
        through (the blurry frame repeated) with a warning.
    """
    for item in source:
        frame, events = item.frame, item.events
        exposure = frame.exposure
        blurry = check_blurry(frame.image, events.width, events.height, frame.name)
        inst = exposure.instants_us(method.n) if per_exposure is None else \
            exposure_instants(exposure, per_exposure)
        inside = events.slice(exposure.start_us, exposure.end_us + 1)
        if len(inside) == 0:
            frames = np.repeat(blurry[None], len(inst), axis=0)
            yield FrameResult(frame.index, frame.name, blurry, exposure,
                              Estimate(frames, inst, None), 0, True,
                              (f"frame {frame.name}: no events in its exposure window "
                               f"[{exposure.start_us}, {exposure.end_us}] µs; passed through "
                               "unchanged",))
            continue
        est = method(blurry, events, exposure, inst)
        warns: tuple[str, ...] = ()
        if est.contrast_estimated and not est.contrast_reliable:
            warns = (f"frame {frame.name}: too few events ({len(inside)}) to estimate the "
                     f"contrast threshold; used c = {est.contrast:.3g} (set --contrast)",)
        yield FrameResult(frame.index, frame.name, blurry, exposure, est, len(inside),
                          False, warns)


# --------------------------------------------------------------------------------------------
# high frame rate


@dataclass(frozen=True, eq=False)
class HfrFrame:
    """One frame of the continuous stream: time (µs), image, and where it came from."""

    t_us: float
    image: np.ndarray
    kind: str  # "exposure" or "gap"
    source: str


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
        results: from :func:`deblur_frames`, in time order.
        recording: where the gaps' events come from (None: no events, cross-fade only).
        fill_gaps: False = exposures only.
        max_gap_frames: most frames per gap (None: 4 × frames per exposure); longer gaps get a
            coarser step and a note.
        contrast: c for the gaps when a result has none (TRMD without in-between frames).
        notes: list that receives one-time remarks for the user.
    """
    prev: FrameResult | None = None
    capped = False
    for res in results:
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
                     "frames than real time would need (raise --max-gap-frames)")


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


# --------------------------------------------------------------------------------------------
# outputs


def clipped_fraction(frames: np.ndarray) -> float:
    """Fraction of values above 1 (they are clipped when written)."""
    return float((frames > 1.0).mean()) if frames.size else 0.0


def write_result_folder(folder: str | Path, result: FrameResult, *, bit_depth: int = 8,
                        compare: bool = False, meta: dict | None = None) -> dict:
    """Write one result into ``folder`` (which must exist): frame_000.png … frame_{K-1}.png,
    sharp.png (the middle frame), timestamps.txt, meta.json, [compare.png]. Returns the meta.
    """
    from .write import write_image, write_json, write_text

    folder = Path(folder)
    frames = result.frames
    width = max(3, len(str(len(frames) - 1)))
    lines = ["# file time_us (event clock)"]
    for k, (img, t) in enumerate(zip(frames, result.instants_us, strict=True)):
        name = f"frame_{k:0{width}d}.png"
        write_image(folder / name, img, bit_depth)
        lines.append(f"{name} {_fmt_us(t)}")
    write_image(folder / "sharp.png", result.middle, bit_depth)
    write_text(folder / "timestamps.txt", "\n".join(lines) + "\n")
    if compare:
        write_image(folder / "compare.png", compare_strip(result.blurry, result.middle),
                    bit_depth)
    info = {
        "frame": result.name,
        "index": result.index,
        "exposure_us": [result.exposure.start_us, result.exposure.end_us],
        "frames": len(frames),
        "instants_us": [float(t) for t in result.instants_us],
        "contrast": result.estimate.contrast,
        "contrast_estimated": result.estimate.contrast_estimated,
        "events": result.num_events,
        "hot_pixels": result.estimate.hot_pixels,
        "passthrough": result.passthrough,
        "clipped_fraction": clipped_fraction(frames),
    }
    full = {**(meta or {}), **info}
    write_json(folder / "meta.json", full)
    return info


def _fmt_us(t: float) -> str:
    return f"{t:.3f}".rstrip("0").rstrip(".")


def compare_strip(blurry: np.ndarray, sharp: np.ndarray, labels=("blurry", "sharp")
                  ) -> np.ndarray:
    """Side-by-side ``blurry | sharp`` (float [0, 1]) with small labels."""
    import cv2

    a = np.clip(blurry, 0, 1).astype(np.float32)
    b = np.clip(sharp, 0, 1).astype(np.float32)
    if a.ndim != b.ndim:
        a, b = (np.repeat(x[..., None], 3, axis=2) if x.ndim == 2 else x for x in (a, b))
    gap = np.ones((a.shape[0], 4, *a.shape[2:]), np.float32)
    strip = np.ascontiguousarray(np.concatenate([a, gap, b], axis=1))
    scale = max(0.35, a.shape[0] / 600)
    # OpenCV draws text on 8-bit images only: draw masks, then paint the float strip
    outline = np.zeros(strip.shape[:2], np.uint8)
    text_mask = np.zeros(strip.shape[:2], np.uint8)
    for text, x in zip(labels, (4, a.shape[1] + 8), strict=True):
        y = int(18 * scale / 0.5)
        cv2.putText(outline, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, 255, 3, cv2.LINE_AA)
        cv2.putText(text_mask, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, 255, 1,
                    cv2.LINE_AA)
    # dark outline under light text: readable on any background
    strip[outline > 127] = 0.0
    strip[text_mask > 127] = 1.0
    return strip
