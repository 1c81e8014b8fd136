"""Evaluation of deblurring methods: figures against ground truth, and without it.

Every method runs as ``trmd deblur`` runs it — the same :class:`~trmd_cli.methods.Method`
objects, through :func:`trmd_cli.deblur.deblur_frames` on raw events, through ``from_bins`` on
binned data — on frames from the same readers (:func:`trmd_cli.read.dataset.open_dataset`).

With ground truth (the trmd HDF5 written by ``trmd simulate``, GOPRO-style HDF5 of the paper's
release, folders of blurry frames + events + sharp frames) every method's 2N+1 output frames,
clipped to [0, 1] as users see them, are compared with the sharp frames:

* PSNR with data range 1, capped at :data:`PSNR_CAP_DB` (identical images); the *sequence*
  figure is the mean of the 2N+1 per-frame PSNRs, not the PSNR of the whole stack;
* SSIM (Wang et al. 2004: 11×11 Gaussian window, σ = 1.5, data range 1; :mod:`trmd_cli.metrics`),
  likewise for the middle frame and as the mean over the 2N+1 frames.

Without ground truth (real recordings): sharpness and noise σ of the middle frame, the share of
the events around mid-exposure its gradients explain
(:func:`~trmd_cli.threshold.explained_share`), and the event consistency of the 2N+1 frames
(:mod:`trmd_cli.metrics`), judged with the contrast the method used (EDI), else the data's true
c, else EDI's estimate for the frame — so that TRMD, and ``blurry`` as the floor, are judged
with a threshold too.

Methods: ``blurry`` (the blurry frame repeated: the floor), every method of
:mod:`trmd_cli.methods` (``edi``: contrast estimated per frame; ``trmd``: RE-Net +
reconstruction; ``motion``: deconvolution along the events' estimated motion), ``edi-true-c``
(EDI given the simulator's true mean contrast, when the data stores it: the baseline the
training targets are defined against) and ``motion-true-path`` (the motion method along the
simulator's true camera path, ``frames/motion``: how much better the motion method would be
with a perfect motion estimate; an error on sets that store no path).

Library code: nothing here prints; notes (skipped methods, LPIPS) travel in the report.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .deblur import deblur_frames, pattern_line
from .errors import InputError
from .fixed_pattern import FixedPattern
from .methods import METHODS as DEBLUR_METHODS
from .methods import REGISTRY, EdiMethod, Method, MethodConfig, make_method, unavailable
from .metrics import (
    LOG_EPS,
    consistency_from_counts,
    interval_counts,
    noise_sigma,
    psnr,
    sharpness,
    ssim,
)
from .oracle import TRUE_PATH, TruePathMethod
from .read.base import Frame, ReadOptions
from .read.dataset import EvalFrame, open_dataset
from .read.folders import FrameWindow
from .report import DatasetReport, EvalReport, FrameScore, MethodResult
from .threshold import explained_share

__all__ = [
    "METHODS",
    "DEFAULT_METHODS",
    "PSNR_CAP_DB",
    "FrameOutputs",
    "parse_methods",
    "protocol",
    "evaluate_dataset",
    "evaluate",
    "lpips_status",
]

#: the floor every method should beat: the blurry frame repeated as each latent frame
BLURRY = "blurry"
#: EDI given the true mean contrast stored with simulated data
TRUE_C = "edi-true-c"
DEFAULT_METHODS = (BLURRY, "edi", "trmd")
#: PSNR of identical images is infinite; capping keeps means and JSON finite
PSNR_CAP_DB = 100.0
#: what the evaluation's own entries are, for the JSON report (the methods say it themselves)
_NOTES = {
    BLURRY: "the blurry frame repeated as every latent frame",
    TRUE_C: "the same EDI given the true mean contrast stored with simulated data",
    TRUE_PATH: TruePathMethod.summary,
}
#: the evaluation's oracle twins: each follows the method it gives the truth to
_TWINS = {EdiMethod.name: TRUE_C, "motion": TRUE_PATH}


def _known() -> tuple[str, ...]:
    """The floor, then every deblurring method, each followed by its oracle twin (EDI by its
    true-c twin, motion by its true-path twin)."""
    out = [BLURRY]
    for m in DEBLUR_METHODS:
        out += [m, _TWINS[m]] if m in _TWINS else [m]
    return tuple(out)


#: every method ``trmd eval`` knows, in the order tables list them
METHODS = _known()


def parse_methods(methods: str | Sequence[str]) -> tuple[str, ...]:
    """``"blurry,edi"`` or a list → validated tuple in the given order, duplicates dropped.

    Raises:
        InputError: an unknown name (the message lists the known ones).
    """
    names = methods.split(",") if isinstance(methods, str) else list(methods)
    out: list[str] = []
    for raw in names:
        m = raw.strip().lower()
        if not m:
            continue
        if m not in METHODS:
            raise InputError(f"unknown method {raw.strip()!r}",
                             hint=f"choose from {', '.join(METHODS)}")
        if m not in out:
            out.append(m)
    if not out:
        raise InputError("no method given", hint=f"choose from {', '.join(METHODS)}")
    return tuple(out)


#: how to read the figures of a set without ground truth (printed under its table, and in the
#: JSON report): the consistency error cannot rank EDI, which is built from the same relation
NO_GT_READING = (
    "sharpness: read it next to noise σ (noise has gradients too). events explained: the "
    "share of the events around mid-exposure that the middle frame's gradients account for, "
    "block by block (edges where the events fired, at their scale; noise does not raise it, "
    "and EDI, made from those events, is favoured). consistency err: how far "
    "log L(k+1) − log L(k) is from c × the events between the two instants; EDI builds its "
    "frames from exactly that relation, so it scores ≈ 0 by construction, and the blurry "
    "frame, which does not change, scores about c: it ranks methods that do not integrate "
    "the events (TRMD and others) against each other, not against EDI.")


def protocol() -> dict[str, Any]:
    """How the figures are computed, for the JSON report."""
    return {
        "clip": [0.0, 1.0],
        "psnr": {"data_range": 1.0, "cap_db": PSNR_CAP_DB,
                 "sequence": "mean of the 2N+1 per-frame PSNRs"},
        "ssim": {"window": "gaussian 11x11", "sigma": 1.5, "data_range": 1.0,
                 "sequence": "mean of the 2N+1 per-frame SSIMs"},
        "sharpness": "mean squared forward differences of the middle frame (gray)",
        "noise": "Immerkaer's white-noise sigma estimate of the middle frame (gray)",
        "explained": "share of the signed events within +-0.03 of the exposure around the "
                     "middle instant (binned: the middle bin) that per-16x16-block "
                     "least-squares fits on the middle frame's log gradients explain "
                     "(sigma 1.5 px on both)",
        "consistency": "mean |dlog L - c*E| over pixels with events, consecutive "
                       f"frames, intensities floored at {LOG_EPS}; c = the method's "
                       "own (EDI), else the true c, else EDI's estimate",
        "reading_without_ground_truth": NO_GT_READING,
        "methods": {m: _NOTES[m] if m in _NOTES else REGISTRY[m].summary for m in METHODS},
    }


@dataclass(frozen=True, eq=False)
class FrameOutputs:
    """What a frame looked like, for compare strips: handed to ``on_frame`` callbacks.

    Attributes:
        dataset: path of the dataset. frame: the input.
        middle: method → middle output frame, clipped to [0, 1].
        scores: method → :class:`~trmd_cli.report.FrameScore`.
    """

    dataset: str
    frame: EvalFrame
    middle: dict[str, np.ndarray] = field(default_factory=dict)
    scores: dict[str, FrameScore] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# Running the methods


@dataclass(frozen=True, eq=False)
class _Output:
    latent: np.ndarray  # (2N+1, H, W[, 3]) [0, 1] intensity, unclipped
    contrast: float | None  # the c the method used, else None
    warnings: tuple[str, ...] = ()


def _build(names: Sequence[str], n: int, weights: str | Path | None, *, device: str = "auto",
           threads: int | None = None, precision: str = "auto",
           built: Mapping[str, Method] | None = None, drop_isolated: bool = True
           ) -> tuple[dict[str, Method], dict[str, str]]:
    """The deblurring methods among ``names`` (those in ``built`` reused), and a note for each
    one that cannot run here."""
    out, skipped = dict(built or {}), {}
    for name in names:
        if name not in DEBLUR_METHODS or name in out:
            continue
        config = MethodConfig(name, n=n, weights=weights, device=device, threads=threads,
                              precision=precision, drop_isolated=drop_isolated)
        why = unavailable(config)
        if why:
            skipped[name] = f"{name} skipped: {why}"
        else:
            out[name] = make_method(config)
    return out, skipped


def _method_for(name: str, frame: EvalFrame, n: int, built: Mapping[str, Method],
                drop_isolated: bool = True) -> Method | None:
    """The method behind an evaluation name for this frame; None for the blurry floor."""
    if name == BLURRY:
        return None
    if name == TRUE_C:
        if frame.contrast is None:
            raise InputError(f"frame {frame.name} stores no true contrast threshold")
        return EdiMethod(n, frame.contrast, hot_pixels=True, drop_isolated=drop_isolated)
    if name == TRUE_PATH:
        if frame.motion is None:
            raise InputError(f"frame {frame.name} stores no true camera path")
        return TruePathMethod(n, frame.motion, hot_pixels=True, drop_isolated=drop_isolated)
    return built[name]


def _pattern(src, total: int) -> FixedPattern | None:
    """The sensor's fixed pattern over the ``total`` frames evaluated, estimated as ``trmd
    deblur`` estimates a recording's (:func:`~trmd_cli.deblur.recording_pattern`); None for
    one frame."""
    from .deblur import RECORDING_CANDIDATES, candidates_of, pattern_from

    if total < 2:
        return None
    return pattern_from(src.blurry_frames(candidates_of(total, RECORDING_CANDIDATES)),
                        src.width, src.height)


def _without(method: Method | None, pattern: FixedPattern | None) -> Method | None:
    """``method`` removing ``pattern`` (a removed one) from every frame; the blurry floor
    (None) is the input as it is."""
    return method if method is None or pattern is None else method.for_pattern(pattern)


def _run(method: Method | None, frame: EvalFrame, n: int) -> _Output:
    """One method on one frame as ``trmd deblur`` runs it; binned data through ``from_bins``."""
    if method is None:
        return _Output(np.repeat(frame.blurry[None], 2 * n + 1, axis=0), None)
    if frame.bins is not None:
        est = method.from_bins(frame.blurry, frame.bins, frame.instants_us)
        return _Output(est.frames, est.contrast)
    win = FrameWindow(Frame(frame.blurry, frame.exposure, frame.index, frame.name), frame.events)
    res = next(deblur_frames([win], method))
    return _Output(res.frames, res.estimate.contrast, res.warnings)


def _edi_contrast(frame: EvalFrame, n: int, drop_isolated: bool = True,
                  pattern: FixedPattern | None = None) -> float:
    """EDI's automatic contrast for one frame, as ``EdiMethod`` settles it."""
    edi = _without(EdiMethod(n, None, hot_pixels=True, drop_isolated=drop_isolated), pattern)
    if frame.bins is not None:
        return float(edi.prepare(frame.blurry, frame.bins).contrast)
    return float(edi.prepare(frame.blurry, frame.events, frame.exposure).contrast)


def _counts(frame: EvalFrame) -> tuple[np.ndarray, np.ndarray]:
    """Signed counts and activity between consecutive latent instants (see
    :func:`trmd_cli.metrics.interval_counts`); binned data: the bins themselves."""
    if frame.bins is not None:
        b = np.asarray(frame.bins, np.float64)
        m = len(frame.instants_us) - 1
        if b.shape[0] != m:  # the counts between consecutive instants (resample_bins)
            from .voxel import resample_bins

            b = resample_bins(b, m).astype(np.float64)
        return b, b != 0
    assert frame.events is not None
    return interval_counts(frame.events, frame.instants_us)


#: half-width of the window around the middle instant whose events the middle frame's
#: gradients should explain, as a fraction of the exposure (the threshold estimate's)
MIDDLE_WINDOW = 0.03


def _middle_counts(frame: EvalFrame, n: int) -> np.ndarray:
    """Signed counts of the events within ±:data:`MIDDLE_WINDOW` of the exposure around the
    middle instant; binned data: the bin that holds mid-exposure."""
    if frame.bins is not None:
        m = frame.bins.shape[0]
        return np.asarray(frame.bins[min(m // 2, m - 1)], np.float64)
    assert frame.events is not None and frame.exposure is not None
    mid, half = float(frame.instants_us[n]), MIDDLE_WINDOW * frame.exposure.duration_us
    return interval_counts(frame.events, [mid - half, mid + half])[0][0]


# --------------------------------------------------------------------------------------------
# Scores


def _score(frame: EvalFrame, latent: np.ndarray, n: int, *, truth: bool, contrast: float | None,
           counts: tuple[np.ndarray, np.ndarray] | None, seconds: float, lpips=None,
           middle_counts: np.ndarray | None = None) -> FrameScore:
    out = np.clip(latent, 0.0, 1.0)
    figs: dict[str, Any] = {"sharpness": sharpness(out[n]), "noise": noise_sigma(out[n]),
                            "contrast": contrast, "seconds": seconds}
    if middle_counts is not None:
        figs["explained"] = explained_share(out[n], middle_counts)
    if counts is not None and contrast is not None:
        figs["consistency"] = consistency_from_counts(out, counts[0], contrast, counts[1])
    if truth and frame.truth is not None:
        gt = frame.truth
        p = [min(psnr(o, g), PSNR_CAP_DB) for o, g in zip(out, gt, strict=True)]
        s = [ssim(o, g) for o, g in zip(out, gt, strict=True)]
        figs.update(psnr_mid=p[n], psnr_seq=float(np.mean(p)), ssim_mid=s[n],
                    ssim_seq=float(np.mean(s)))
        if lpips is not None:
            ls = lpips(out, gt)
            figs.update(lpips_mid=ls[n], lpips_seq=float(np.mean(ls)))
    return FrameScore(frame.index, frame.name, **figs)


def lpips_status() -> tuple[bool, str]:
    """Whether LPIPS can run without downloading anything: (available, note)."""
    import importlib.util

    if importlib.util.find_spec("lpips") is None:
        return False, "LPIPS skipped: the 'lpips' package is not installed"
    try:
        import torch

        hub = Path(torch.hub.get_dir()) / "checkpoints"
    except Exception:  # noqa: BLE001 - any failure means "not available"
        return False, "LPIPS skipped: torch is not usable"
    if not list(hub.glob("alexnet-*.pth")):
        return False, ("LPIPS skipped: its AlexNet backbone weights are not on disk "
                       f"({hub}) and nothing is downloaded")
    return True, "LPIPS: AlexNet variant (lpips package)"


def _lpips_fn():
    """(2N+1, H, W[, 3]) pair → per-frame LPIPS list (inputs in [0, 1])."""
    import lpips as lp
    import torch

    net = lp.LPIPS(net="alex", verbose=False).eval()

    def fn(out: np.ndarray, gt: np.ndarray) -> list[float]:
        def t(a):
            a = torch.from_numpy(np.ascontiguousarray(a, np.float32))
            a = a[:, None].expand(-1, 3, -1, -1) if a.ndim == 3 else a.permute(0, 3, 1, 2)
            return a * 2 - 1
        with torch.inference_mode():
            return [float(v) for v in net(t(out), t(gt)).flatten()]

    return fn


# --------------------------------------------------------------------------------------------
# Datasets


def evaluate_dataset(
    path: str | Path,
    methods: str | Sequence[str] = DEFAULT_METHODS,
    n: int = 3,
    limit: int | None = None,
    weights: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
    *,
    ground_truth: bool | None = None,
    options: ReadOptions | None = None,
    built: Mapping[str, Method] | None = None,
    lpips: bool | None = None,
    on_frame: Callable[[FrameOutputs], None] | None = None,
    precision: str = "auto",
    drop_isolated: bool = True,
    fixed_pattern: bool = True,
) -> DatasetReport:
    """Run the methods on one dataset and score them.

    Args:
        path: a dataset (see :func:`~trmd_cli.read.dataset.open_dataset`).
        methods: names from :data:`METHODS` (a comma-separated string or a sequence).
        n: 2N+1 latent frames (must match the ground truth and the weights).
        limit: evaluate only the first ``limit`` frames.
        weights: RE-Net weights for ``trmd``; None = the shipped default (``trmd`` is skipped
            with a note when there is none).
        progress: called as ``progress(done, total)`` after each frame.
        ground_truth: True = require ground truth (InputError without it); False = figures
            without ground truth even when it exists; None = whichever the dataset allows.
        options: how to read event files (time unit, columns …).
        built: deblurring methods already built, by name (shared across datasets by
            :func:`evaluate`); the others are built here, overriding nothing.
        lpips: compute LPIPS (None = when :func:`lpips_status` says it can).
        on_frame: called with each frame's :class:`FrameOutputs` (compare strips).
        precision: the network's arithmetic when weights are loaded here
            (:mod:`trmd_cli.precision`).
        fixed_pattern: every method but the blurry floor gets the frames without the sensor's
            fixed pattern, estimated over the frames evaluated as ``trmd deblur`` estimates a
            recording's (a set of unrelated samples shows none: nothing is removed).
    Returns:
        :class:`~trmd_cli.report.DatasetReport`.
    Raises:
        InputError: unknown method, ``ground_truth=True`` on data without it, bad ``limit``.
        FormatError / WeightsError: unreadable data or weights.
    """
    methods = parse_methods(methods)
    if limit is not None and limit < 1:
        raise InputError(f"`limit` must be ≥ 1, got {limit}")
    notes: list[str] = []
    with open_dataset(path, n, options) as src:
        if ground_truth and not src.has_ground_truth:
            raise InputError("holds no ground truth (sharp frames)", path=src.path,
                             hint="evaluate it with `ground_truth=False` (sharpness, noise and "
                                  "event consistency), or give a set made by `trmd simulate`")
        use_gt = src.has_ground_truth if ground_truth is None else ground_truth
        if ground_truth is None and not use_gt:
            notes.append(f"{src.path.name}: no ground truth: reporting sharpness, noise and event "
                         "consistency instead")
        notes.extend(src.notes)
        skipped: dict[str, str] = {}
        if TRUE_PATH in methods and not src.has_true_motion:
            raise InputError(f"holds no true camera path (frames/motion), which {TRUE_PATH} "
                             "needs", path=src.path,
                             hint=f"drop {TRUE_PATH} from the methods, or evaluate a set that "
                                  "`trmd simulate` made from a still image (videos, recordings "
                                  "and older files store no path)")
        if TRUE_C in methods and not src.has_true_contrast:
            skipped[TRUE_C] = ("edi-true-c skipped: the data stores no true contrast "
                               "threshold (only simulated sets do)")
        built, unable = _build(methods, n, weights, precision=precision, built=built,
                               drop_isolated=drop_isolated)
        skipped.update(unable)
        notes.extend(skipped.values())
        if not src.has_raw_events and any(built[m].needs.timing for m in methods if m in built):
            notes.append("the data is binned (no event times): the network's timing inputs get "
                         "the counts instead — expect less than on raw events")
        lpips_fn = None
        if use_gt and lpips is not False:
            ok, note = lpips_status()
            if ok:
                lpips_fn = _lpips_fn()
            elif lpips:
                raise InputError(note)
        active = [m for m in methods if m not in skipped]
        scores: dict[str, list[FrameScore]] = {m: [] for m in methods}
        total = len(src) if limit is None else min(limit, len(src))
        pattern = _pattern(src, total) if fixed_pattern and active else None
        if pattern is not None:
            notes.append(f"{src.path.name}: {pattern_line(pattern)}")
            pattern = pattern if pattern.removed else None
        done = 0
        for frame in src.frames(limit):
            runs: dict[str, tuple[_Output, float]] = {}
            for m in active:
                t0 = time.perf_counter()
                runs[m] = (_run(_without(_method_for(m, frame, n, built, drop_isolated),
                                         pattern), frame, n),
                           time.perf_counter() - t0)
                notes.extend(runs[m][0].warnings)
            counts, middle = _counts(frame), _middle_counts(frame, n)
            # methods without a threshold of their own are judged with the data's true c,
            # else the c EDI's automatic estimate picks for this frame
            ref_c = frame.contrast
            if ref_c is None and active:
                edi = runs.get(EdiMethod.name)
                ref_c = edi[0].contrast if edi is not None and edi[0].contrast is not None \
                    else _edi_contrast(frame, n, drop_isolated, pattern)
            outputs = FrameOutputs(str(src.path), frame)
            for m, (out, seconds) in runs.items():
                c = out.contrast if out.contrast is not None else ref_c
                score = _score(frame, out.latent, n, truth=use_gt, contrast=c, counts=counts,
                               seconds=seconds, lpips=lpips_fn, middle_counts=middle)
                scores[m].append(score)
                outputs.middle[m] = np.clip(out.latent[n], 0.0, 1.0)
                outputs.scores[m] = score
            if on_frame is not None:
                on_frame(outputs)
            done += 1
            if progress is not None:
                progress(done, total)
        return DatasetReport(
            str(src.path), src.kind, bool(use_gt), n, (src.width, src.height), done,
            tuple(MethodResult(m, tuple(scores[m]), skipped.get(m)) for m in methods),
            tuple(dict.fromkeys(notes)))


def evaluate(
    paths: Sequence[str | Path],
    methods: str | Sequence[str] = DEFAULT_METHODS,
    n: int = 3,
    limit: int | None = None,
    weights: str | Path | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    *,
    ground_truth: bool | None = None,
    options: ReadOptions | None = None,
    lpips: bool | None = None,
    on_frame: Callable[[FrameOutputs], None] | None = None,
    device: str = "auto",
    threads: int | None = None,
    precision: str = "auto",
    drop_isolated: bool = True,
    fixed_pattern: bool = True,
) -> EvalReport:
    """:func:`evaluate_dataset` over several datasets, building the methods once (weights on
    ``device``, with ``threads`` torch CPU threads, the network in ``precision``).

    ``progress`` is called as ``progress(dataset_path, done, total)``. ``drop_isolated``:
    every method's EDI leaves out the events no neighbour corroborates
    (:class:`~trmd_cli.methods.MethodConfig`), the true-c and true-path twins included.
    ``fixed_pattern``: see :func:`evaluate_dataset`.
    """
    methods = parse_methods(methods)
    built, skipped = _build(methods, n, weights, device=device, threads=threads,
                            precision=precision, drop_isolated=drop_isolated)
    notes = list(skipped.values())
    reports = []
    for p in paths:
        cb = None if progress is None else (lambda d, t, _p=str(p): progress(_p, d, t))
        reports.append(evaluate_dataset(
            p, methods, n, limit, weights, cb, ground_truth=ground_truth, options=options,
            built=built, lpips=lpips, on_frame=on_frame, drop_isolated=drop_isolated,
            fixed_pattern=fixed_pattern))
    if lpips is not False and any(r.ground_truth for r in reports):
        ok, note = lpips_status()
        if not ok:
            notes.append(note)
    return EvalReport(tuple(reports), methods, n, limit, tuple(notes), protocol())
