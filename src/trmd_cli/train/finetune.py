"""Fine-tuning RE-Net on a user's own recordings, without ground truth.

A real camera has no sharp frames to train on, and Eq. 11 makes the mean of the 2N+1 frames
equal the blurry frame whatever the network predicts, so plain blur consistency says nothing.
What does carry a signal:

* **re-blur** (``reblur``): the middle frame moved along the exposure's motion — estimated from
  the events by contrast maximisation (:func:`trmd_cli.motion.estimate_motion`) — and averaged
  must give the blurry frame back; only a sharp middle frame does;
* **warp** (``warp``): each frame L(k) must match the middle frame carried to instant k;
* **the deconvolution** (``deconv``): the frames against the guarded motion-aware deconvolution
  of the blurry frame (:func:`trmd_cli.deconv.motion_deblur`) where its guard trusts it — the
  re-blur constraint solved once per window with a gradient prior, which the network's own
  gradient of the re-blur loss (a small difference on top of the sensor's noise) finds slowly;
* **events** (``event_consistency``): log L(k+1) − log L(k) against c × the events between the
  instants, c from the window's threshold estimate. Off by default: on noisy simulated sensors
  the estimated c is biased (0.65–0.96 for a true 0.6) and the true frames score worse on this
  term than the shipped network's;
* a pull towards the starting weights (``anchor``), so a few hundred windows cannot wreck what
  the simulated training taught.

Windows whose events show no reliable motion (the contrast gain of the warped events below
``min_confidence``) have their motion terms masked out, and so has every pixel where the
deconvolution's guard fell back to EDI (re-blurring along the motion did not give the blurry
frame back there: the motion is wrong, e.g. an object moving on its own): only the event
term, when it is on, learns from them. Part of the windows is held out: the losses on
them, before and after, say whether the fine-tuning helped on frames it never trained on.

The pieces: :func:`prepare_windows` (read → window → voxels, c and motion, one window at a
time), :func:`split_windows`, :func:`crop_batch` / :func:`window_batch` (the tensors the
losses read), :func:`held_out_losses`, and :func:`finetune`, the loop.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import InputError
from ..motion.model import GlobalMotion
from .recipe import LossSpec, Recipe

__all__ = ["FinetuneConfig", "Window", "FinetuneResult", "DEFAULT_LOSSES", "input_groups",
           "prepare_windows", "split_windows", "motion_grid", "crop_batch", "window_batch",
           "held_out_losses", "finetune"]

#: the losses that read the exposure's motion (masked where it is not trusted)
MOTION_TERMS = ("reblur", "warp", "deconv")
#: loss weights of a fine-tuning run (registered losses, :mod:`.losses`)
DEFAULT_LOSSES: Mapping[str, float] = {"reblur": 1.0, "warp": 0.25, "deconv": 1.0,
                                       "event_consistency": 0.0}


@dataclass(frozen=True)
class FinetuneConfig:
    """A fine-tuning run's settings.

    Attributes:
        steps: optimiser steps.
        crop: training crops, pixels (square; smaller frames are used whole).
        batch_size: crops per step.
        lr: Adam's learning rate (constant after a short warm-up).
        losses: weight per registered loss; only losses that need no sharp frames.
        anchor: weight of the mean squared distance of the weights from the starting ones,
            relative to the mean squared starting weight.
        holdout: fraction of the windows held out (at least one when there are two or more).
        max_windows: at most this many windows, taken evenly over the inputs' frames.
        min_confidence: motion losses only on windows whose motion has at least this contrast
            gain (:attr:`~trmd_cli.motion.GlobalMotion.confidence`; 1 = the events say nothing).
        max_instants: J, instants of the re-blur (at most ½ px of motion apart, 3 ≤ J ≤ this).
        contrast: the sensor's threshold c (log intensity per event); None = estimate it per
            window as ``trmd deblur`` does.
        hot_pixels: ignore the events of hot pixels (c and motion).
        fixed_pattern: remove each recording's sensor pattern from its frames, as ``trmd
            deblur`` does before the network sees them (:mod:`trmd_cli.fixed_pattern`).
        penalty, charbonnier_eps, log_eps: as in a training recipe's ``[loss]`` table.
        seed: crops and window order.
        trainable: names of the network's top-level parts that train (e.g. ``("refine",
            "head")``); empty = all of them. Fewer parameters fit a few windows less closely.
        oracle: allow the supervised losses (``sequence``, ``middle``, ``residual``), for
            experiments on simulated windows that carry their sharp frames
            (:attr:`Window.sharp`): what ground truth would teach in the same run, the
            ceiling of the losses that need none. ``trmd finetune`` never sets it.
    """

    steps: int = 300
    crop: int = 128
    batch_size: int = 4
    lr: float = 3e-4
    losses: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_LOSSES))
    anchor: float = 0.01
    holdout: float = 0.2
    max_windows: int = 240
    min_confidence: float = 1.1
    max_instants: int = 48
    contrast: float | None = None
    hot_pixels: bool = True
    fixed_pattern: bool = True
    penalty: str = "charbonnier"
    charbonnier_eps: float = 1e-3
    log_eps: float = 1e-2
    seed: int = 0
    trainable: tuple[str, ...] = ()
    oracle: bool = False

    def __post_init__(self) -> None:
        from .losses import LOSSES, SUPERVISED

        checks = [(self.steps >= 0, "steps", "must be ≥ 0"),
                  (self.crop >= 16, "crop", "must be ≥ 16 pixels"),
                  (self.batch_size >= 1, "batch_size", "must be ≥ 1"),
                  (self.lr > 0, "lr", "must be > 0"),
                  (self.anchor >= 0, "anchor", "must be ≥ 0"),
                  (0 <= self.holdout < 1, "holdout", "must be in [0, 1)"),
                  (self.max_windows >= 1, "max_windows", "must be ≥ 1"),
                  (self.max_instants >= 3, "max_instants", "must be ≥ 3"),
                  (self.contrast is None or self.contrast > 0, "contrast", "must be > 0")]
        for ok, name, why in checks:
            if not ok:
                raise InputError(f"finetune `{name}` {why}, got {getattr(self, name)!r}")
        for name, w in self.losses.items():
            if name not in LOSSES:
                raise InputError(f"unknown loss {name!r}",
                                 hint=f"known: {', '.join(sorted(set(LOSSES) - SUPERVISED))}")
            if name in SUPERVISED and not self.oracle:
                raise InputError(f"loss {name!r} needs sharp frames, which fine-tuning has not",
                                 hint="use reblur, warp, deconv, event_consistency or "
                                 "blur_consistency")
            if w < 0:
                raise InputError(f"the weight of loss {name!r} must be ≥ 0, got {w}")
        if not any(w > 0 for w in self.losses.values()):
            raise InputError("no fine-tuning loss has a positive weight")

    def recipe(self) -> Recipe:
        """The losses' options as the loss functions read them."""
        return Recipe(loss=LossSpec(weights=dict(self.losses), penalty=self.penalty,
                                    charbonnier_eps=self.charbonnier_eps,
                                    contrast=self.contrast or 0.2, log_eps=self.log_eps))


@dataclass(frozen=True, eq=False)
class Window:
    """One exposure, ready for the losses.

    Attributes:
        name: ``<input>:<frame>``, for messages and the picture.
        blurry: (H, W) float32 [0, 1] (colour frames as luma: the network is gray).
        voxels: (2N, H, W) SCER voxels; levels: their sub-bin timing, or None.
        contrast: c, log intensity per event (given or estimated).
        motion: the exposure's global motion (pixels, exposure fractions).
        trusted: the motion is reliable enough for the motion losses (the warped events'
            contrast gain, and the guard kept some of the deconvolution along it).
        deconv: (2N+1, H, W) the motion-aware deconvolution at the network's instants
            (:func:`trmd_cli.deconv.motion_deblur`), for the ``deconv`` loss; None when the
            run does not use it.
        deconv_weight: (2N+1, H, W) [0, 1], the deconvolution's share of each of those frames
            (0 where its guard fell back to EDI); it also masks the re-blur (middle frame's)
            and warp (frame k's) terms: where re-blurring along the motion does not explain
            the blurry frame, that motion teaches nothing.
        sharp: (2N+1, H, W) [0, 1] the true frames of a simulated window, for oracle
            experiments only (:attr:`FinetuneConfig.oracle`); None from :func:`prepare_windows`.
    """

    name: str
    blurry: np.ndarray
    voxels: np.ndarray
    levels: np.ndarray | None
    contrast: float
    motion: GlobalMotion
    trusted: bool
    deconv: np.ndarray | None = None
    deconv_weight: np.ndarray | None = None
    sharp: np.ndarray | None = None

    @property
    def n(self) -> int:
        return self.voxels.shape[0] // 2


@dataclass(frozen=True)
class FinetuneResult:
    """What a run did.

    Attributes:
        model: the fine-tuned network (on the CPU, in eval mode).
        meta: the weights file's metadata (the starting weights' plus ``finetune``).
        windows, held_out: how many windows trained, how many were held out.
        trusted: of the training windows, how many had a motion the motion losses used.
        before, after: each loss's mean over the held-out windows (whole frames), with the
            starting and with the fine-tuned weights; ``total`` is the weighted sum.
        seconds: wall time of preparation and training.
        example: (blurry, before, after) middle frames of the first held-out window, and its
            name; None without held-out windows.
    """

    model: torch.nn.Module
    meta: dict[str, Any]
    windows: int
    held_out: int
    trusted: int
    before: dict[str, float]
    after: dict[str, float]
    seconds: float
    example: tuple[str, np.ndarray, np.ndarray, np.ndarray] | None


def input_groups(inputs: Sequence[str | Path]) -> list[list[Path]]:
    """The inputs as recordings: each of several recordings (or of a folder of them) on its
    own, else all inputs as one of ``trmd deblur``'s layouts (IMAGE EVENTS, a frames folder …)."""
    from ..batch import recordings_in

    paths = [Path(p) for p in inputs]
    found = recordings_in(paths)
    return [[p] for p in found] if found else [paths]


def _luma(image: np.ndarray) -> np.ndarray:
    from .losses import LUMA

    if image.ndim == 3:
        return (image @ np.array(LUMA, np.float32)).astype(np.float32)
    return image


def prepare_windows(groups: Sequence[Sequence[str | Path]], n: int, *, timing: bool,
                    config: FinetuneConfig, read_options=None,
                    exposure: Sequence[float] | None = None, offset_us: int = 0,
                    on_window: Callable[[int, int], None] | None = None
                    ) -> tuple[list[Window], list[str]]:
    """Read every group's frames and settle what the losses need for each window.

    Args:
        groups: inputs of each recording (:func:`input_groups`). n: the network's N.
        timing: the network takes the voxels' sub-bin timing (compute the levels).
        read_options: :class:`~trmd_cli.read.base.ReadOptions` for the readers.
        exposure, offset_us: as :func:`~trmd_cli.read.inputs.open_inputs` takes them (a window
            for an image and its events; a shift of every window, µs).
        on_window: called with (done, total) after each window, for progress.
    Returns:
        the windows and the notes the user should hear (readers' warnings, skipped frames).
    Binned events (no event times) get their motion from events spread evenly over each bin.
    Raises:
        InputError: no input frame has events in its exposure.
    """
    from ..deblur import pattern_line, recording_pattern
    from ..methods import EdiMethod
    from ..read.inputs import open_inputs

    notes: list[str] = []
    edi = EdiMethod(n, config.contrast, config.hot_pixels)
    windows: list[Window] = []
    skipped = 0
    # every input opened once (some readers decode a whole file to index it), kept open
    # while the frames are counted and then read
    with ExitStack() as stack:
        opened = []
        for paths in groups:
            ins = stack.enter_context(open_inputs(list(paths), read_options, exposure=exposure,
                                                  offset_us=offset_us))
            pattern = recording_pattern(ins.source) if config.fixed_pattern else None
            if pattern is not None:
                notes.append(f"{Path(paths[0]).name}: {pattern_line(pattern)}")
            opened.append((Path(paths[0]).name, ins, pattern))
            notes.extend(ins.warnings)
            if ins.binned:
                notes.append(f"{Path(paths[0]).name}: binned events have no event times; the "
                             "motion is estimated from events spread evenly over each bin")
        total = sum(len(ins.source) for _, ins, _ in opened)
        # evenly over all frames of all inputs, at most max_windows
        take = set(np.unique(np.linspace(0, total - 1, min(total, config.max_windows))
                             .round().astype(int)).tolist()) if total else set()
        seen = 0
        for source_name, ins, pattern in opened:
            for i, item in enumerate(ins.source):
                if seen + i not in take:
                    continue
                frame = item.frame
                if ins.binned:
                    win = _binned_window(item.bins, frame, n, edi, config, pattern)
                else:
                    win = _event_window(item.events, frame, n, timing, edi, config, pattern)
                if win is None:
                    skipped += 1
                    continue
                windows.append(replace(win, name=f"{source_name}:{frame.name}"))
                if on_window is not None:
                    on_window(len(windows) + skipped, len(take))
            seen += len(ins.source)
    if skipped:
        notes.append(f"{skipped} frame(s) without events in their exposure were left out")
    if not windows:
        raise InputError("no frame of the inputs has events in its exposure window",
                         path=groups[0][0] if groups and groups[0] else None,
                         hint="check the exposure windows and the time offset")
    return windows, notes


def _blurry(frame, width: int, height: int, pattern) -> tuple[np.ndarray, float | None]:
    """A window's blurry frame as the network sees it (luma, without the recording's fixed
    pattern), and the noise σ its deconvolution is weighed by (None: measured on it)."""
    from ..edi import check_blurry
    from ..methods import deconv_noise

    recorded = np.clip(check_blurry(frame.image, width, height, frame.name), 0.0, 1.0)
    if pattern is None or not pattern.removed:
        return _luma(recorded), None
    b = _luma(pattern.removed_from(recorded))
    return b, deconv_noise(_luma(recorded), b)


def _event_window(events, frame, n: int, timing: bool, edi, config: FinetuneConfig,
                  pattern=None) -> Window | None:
    """A window of events with times (None: no event in the exposure); ``pattern``: the
    recording's fixed pattern, removed from its frame."""
    from ..voxel import scer_levels, scer_voxels

    span = frame.exposure
    if len(events.within(span)) == 0:
        return None
    b, noise = _blurry(frame, events.width, events.height, pattern)
    prep = edi.prepare(b, events, span)
    motion, trusted, teacher = _motion_and_teacher(b, events, span, n, prep, config, noise)
    # the per-pixel sort c was settled with serves the voxels and levels too
    return Window(frame.name, b.astype(np.float32),
                  scer_voxels(events, span, n, window=prep.window),
                  scer_levels(events, span, n, window=prep.window) if timing else None,
                  float(prep.contrast), motion, trusted, *teacher)


def _binned_window(bins: np.ndarray, frame, n: int, edi, config: FinetuneConfig,
                   pattern=None) -> Window | None:
    """A window of binned events: the network's inputs and c as ``TrmdMethod.from_bins``
    gives them in use (voxels from the counts, the counts as timing levels), the motion and
    the deconvolution from events spread evenly over each bin (:func:`~trmd_cli.voxel.
    spread_bins`). None: no event in the bins. ``pattern``: as for :func:`_event_window`."""
    from ..methods import EdiMethod
    from ..voxel import resample_bins, scer_from_bins, spread_bins

    counts = np.asarray(bins, np.float32)
    if not np.any(counts):
        return None
    height, width = counts.shape[1:]
    b, noise = _blurry(frame, width, height, pattern)
    c = float(edi.prepare(b, counts).contrast)
    events, span = spread_bins(counts)
    # binned EDI has no hot-pixel mask (no per-event information to judge by): nor here
    prep = EdiMethod(n, c, hot_pixels=False).prepare(b, events, span)
    motion, trusted, teacher = _motion_and_teacher(b, events, span, n, prep, config, noise)
    two_n = 2 * n
    voxels = scer_from_bins(counts if counts.shape[0] == two_n else
                            resample_bins(counts, two_n))
    return Window(frame.name, b.astype(np.float32), np.asarray(voxels, np.float32), None, c,
                  motion, trusted, *teacher)


def _motion_and_teacher(blurry, events, exposure, n: int, prep, config: FinetuneConfig,
                        noise: float | None = None
                        ) -> tuple[GlobalMotion, bool, tuple[Any, Any]]:
    """The exposure's motion, whether it may teach, and the guarded deconvolution along it
    ((None, None) when no motion term is on). A motion the events show (contrast gain ≥
    ``min_confidence``) still teaches nothing when the guard kept none of the deconvolution:
    re-blurring along it explains the blurry frame nowhere."""
    from ..motion.cmax import estimate_motion

    motion = estimate_motion(events, exposure, prep.hot)
    trusted = bool(motion.confidence >= config.min_confidence)
    if not any(config.losses.get(k, 0) > 0 for k in MOTION_TERMS):
        return motion, trusted, (None, None)
    teacher = _deconvolved(blurry, events, exposure, n, prep, motion, trusted, noise)
    return motion, trusted and float(teacher[1].mean()) >= 0.01, teacher


def _deconvolved(blurry, events, exposure, n: int, prep, motion, trusted: bool,
                 noise: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The guarded motion-aware deconvolution at the instants k/2N and its share per frame
    (``noise``: see :func:`~trmd_cli.methods.motion_frames`)."""
    from ..methods import motion_frames

    fr = np.arange(2 * n + 1) / (2 * n)
    if not trusted:
        lat = prep.model.latent(blurry, np.append(fr, 0.5), prep.contrast)[:-1]
        return lat.astype(np.float32), np.zeros_like(lat, np.float32)
    _, res = motion_frames(blurry, events, exposure, fr, prep, motion, noise)
    weight = np.zeros_like(res.frames, np.float32) if res.weights is None else res.weights
    return res.frames.astype(np.float32), weight.astype(np.float32)


def split_windows(windows: Sequence[Window], holdout: float
                  ) -> tuple[list[Window], list[Window]]:
    """(training, held-out): every k-th window held out, k = round(1 / holdout), starting
    half-way into the first stride so both ends of a recording train."""
    if holdout <= 0 or len(windows) < 2:
        return list(windows), []
    stride = max(2, int(round(1.0 / holdout)))
    held = set(range(min(stride // 2, len(windows) - 1), len(windows), stride))
    return ([w for i, w in enumerate(windows) if i not in held],
            [w for i, w in enumerate(windows) if i in held])


def motion_grid(motion, fractions: np.ndarray, box: tuple[int, int, int, int]
                ) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel of a crop was in the middle frame at ``fractions`` of the exposure.

    Args:
        motion: anything with ``to_middle(fractions, x, y)`` (pixels).
        fractions: (K,) instants, exposure fractions (0 = start, 1 = end).
        box: (x0, y0, w, h) of the crop on the sensor, pixels.
    Returns:
        ``grid_sample`` coordinates (K, h, w, 2) float32 of the crop (corners aligned), and
        (K, h, w) bool: the point lies inside the crop.
    """
    x0, y0, w, h = box
    ys, xs = np.mgrid[y0:y0 + h, x0:x0 + w].astype(np.float64)
    u = np.asarray(fractions, np.float64)[:, None, None]
    xm, ym = motion.to_middle(u, xs[None], ys[None])
    cx, cy = np.broadcast_arrays(xm - x0, ym - y0)
    inside = (cx >= 0) & (cx <= w - 1) & (cy >= 0) & (cy <= h - 1)
    grid = np.stack([2.0 * cx / max(w - 1, 1) - 1.0, 2.0 * cy / max(h - 1, 1) - 1.0], -1)
    return grid.astype(np.float32), inside


def _reblur_instants(motion: GlobalMotion, width: int, height: int, cap: int) -> int:
    """J: instants at most ½ px of motion apart, 3 ≤ J ≤ ``cap``."""
    disp = motion.max_displacement_px(width, height)
    return min(max(3, int(math.ceil(disp / 0.5)) + 1), cap)


def _window_tensors(win: Window, box: tuple[int, int, int, int], j: int) -> dict[str, Any]:
    x0, y0, w, h = box
    n = win.n
    sl = (slice(y0, y0 + h), slice(x0, x0 + w))
    fr = (np.arange(j) + 0.5) / j
    rg, rin = motion_grid(win.motion, fr, box)
    wg, win_in = motion_grid(win.motion, np.arange(2 * n + 1) / (2 * n), box)
    trust = 1.0 if win.trusted else 0.0
    reblur_mask = (rin.all(0) * trust)[None]
    warp_mask = (win_in * trust)[:, None]
    if win.deconv_weight is not None:
        # where re-blurring along the motion does not give the blurry frame back (the guard
        # fell back to EDI) the motion is wrong there: it must not teach through any term
        guard = win.deconv_weight[:, None, sl[0], sl[1]]
        reblur_mask = reblur_mask * guard[n]
        warp_mask = warp_mask * guard
    out = {"blurry": win.blurry[sl][None], "voxels": win.voxels[:, sl[0], sl[1]],
           "contrast": np.float32(win.contrast),
           "reblur_grid": rg, "reblur_mask": reblur_mask.astype(np.float32),
           "warp_grid": wg, "warp_mask": warp_mask.astype(np.float32)}
    if win.levels is not None:
        out["levels"] = win.levels[:, sl[0], sl[1]]
    if win.deconv is not None and win.deconv_weight is not None:
        out["deconv"] = win.deconv[:, None, sl[0], sl[1]]
        out["deconv_mask"] = win.deconv_weight[:, None, sl[0], sl[1]]
    if win.sharp is not None:
        out["sharp"] = win.sharp[:, None, sl[0], sl[1]]
    return out


def _stack(items: Sequence[dict[str, Any]]) -> dict[str, torch.Tensor]:
    return {k: torch.from_numpy(np.ascontiguousarray(np.stack([it[k] for it in items])))
            for k in items[0]}


def crop_batch(windows: Sequence[Window], rng: np.random.Generator, batch_size: int,
               crop: int, max_instants: int) -> dict[str, torch.Tensor]:
    """``batch_size`` random crops of random windows, as the losses read them.

    All crops of a batch share one J (the largest the windows' motions need), so that their
    grids stack.
    """
    picks = [windows[int(i)] for i in rng.integers(0, len(windows), batch_size)]
    height, width = picks[0].blurry.shape
    cw, ch = min(crop, width), min(crop, height)
    j = max(_reblur_instants(w.motion, width, height, max_instants) for w in picks)
    items = []
    for win in picks:
        x0 = int(rng.integers(0, width - cw + 1))
        y0 = int(rng.integers(0, height - ch + 1))
        items.append(_window_tensors(win, (x0, y0, cw, ch), j))
    return _stack(items)


def window_batch(win: Window, max_instants: int) -> dict[str, torch.Tensor]:
    """One whole window as a batch of one."""
    height, width = win.blurry.shape
    j = _reblur_instants(win.motion, width, height, max_instants)
    return _stack([_window_tensors(win, (0, 0, width, height), j)])


def _outputs(model: torch.nn.Module, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    from ..reconstruct import reconstruct
    from .steps import forward

    residuals = forward(model, batch, needs=model.needs)
    return {"residuals": residuals, "latent": reconstruct(batch["blurry"], residuals)}


def held_out_losses(model: torch.nn.Module, windows: Sequence[Window],
                    config: FinetuneConfig) -> dict[str, float]:
    """Each loss's mean over ``windows`` (whole frames), and ``total``, their weighted sum."""
    from .losses import total_loss

    recipe = config.recipe()
    sums: dict[str, float] = {}
    with torch.inference_mode():
        for win in windows:
            batch = window_batch(win, config.max_instants)
            total, parts = total_loss(_outputs(model, batch), batch, recipe)
            sums["total"] = sums.get("total", 0.0) + float(total)
            for k, v in parts.items():
                sums[k] = sums.get(k, 0.0) + float(v)
    return {k: v / max(len(windows), 1) for k, v in sums.items()}


def _middle(model: torch.nn.Module, win: Window) -> np.ndarray:
    with torch.inference_mode():
        latent = _outputs(model, window_batch(win, 3))["latent"]
    return latent[0, win.n, 0].clamp(0, 1).numpy()


def _freeze_norm(model: torch.nn.Module) -> None:
    # a few crops of one camera make poor batch statistics: keep the trained ones
    for m in model.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.eval()


def _check_parts(model: torch.nn.Module, names: Sequence[str]) -> dict[str, torch.nn.Module]:
    parts = dict(model.named_children())
    unknown = [n for n in names if n not in parts]
    if unknown:
        raise InputError(f"the network has no part named {', '.join(unknown)}",
                         hint=f"its parts: {', '.join(parts)}")
    return parts


def _trainable(model: torch.nn.Module, names: Sequence[str]) -> list[torch.nn.Parameter]:
    """The parameters that train (the others are frozen): all, or those of the named parts."""
    if not names:
        return list(model.parameters())
    parts = _check_parts(model, names)
    for p in model.parameters():
        p.requires_grad_(False)
    params = [p for n in names for p in parts[n].parameters()]
    for p in params:
        p.requires_grad_(True)
    return params


def tune(model: torch.nn.Module, windows: Sequence[Window], config: FinetuneConfig, *,
         progress: Callable[[str, int, int, dict[str, float]], None] | None = None,
         every: Callable[[int], None] | None = None) -> None:
    """``config.steps`` optimiser steps of ``model`` on random crops of ``windows``, in place.

    Batch normalisation keeps its trained statistics; the weights are pulled towards where
    they started (``config.anchor``). ``every(step)`` is called after each step (a hook for
    figures along the way); the model is left in eval mode.
    """
    from .losses import total_loss

    params = _trainable(model, config.trainable)
    start = [p.detach().clone() for p in params]
    scale = float(torch.cat([p.flatten() for p in start]).square().mean()) or 1.0
    opt = torch.optim.Adam(params, lr=config.lr)
    recipe = config.recipe()
    rng = np.random.default_rng(config.seed)
    torch.manual_seed(config.seed)
    warm = max(1, min(20, config.steps // 10))
    say = progress or (lambda *a: None)
    model.train()
    _freeze_norm(model)
    for step in range(config.steps):
        for g in opt.param_groups:
            g["lr"] = config.lr * min(1.0, (step + 1) / warm)
        batch = crop_batch(windows, rng, config.batch_size, config.crop, config.max_instants)
        loss, parts = total_loss(_outputs(model, batch), batch, recipe)
        if config.anchor > 0:
            drift = sum((p - p0).square().sum() for p, p0 in zip(params, start))
            count = sum(p.numel() for p in start)
            loss = loss + config.anchor * drift / (count * scale)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        if every is not None:
            every(step + 1)
        say("train", step + 1, config.steps, {"loss": float(loss.detach()),
                                               **{k: float(v) for k, v in parts.items()}})
    model.eval()


def finetune(inputs: Sequence[str | Path], *, weights: str | Path | None = None,
             config: FinetuneConfig | None = None, read_options=None,
             exposure: Sequence[float] | None = None, offset_us: int = 0,
             threads: int | None = None,
             progress: Callable[[str, int, int, dict[str, float]], None] | None = None
             ) -> tuple[FinetuneResult, list[str]]:
    """Fine-tune ``weights`` (None = the shipped ones) on ``inputs`` without ground truth.

    Args:
        inputs: what ``trmd deblur`` accepts (:func:`input_groups`).
        read_options, exposure, offset_us: how to read them (see :func:`prepare_windows`).
        threads: torch CPU threads (None = torch's default).
        progress: called as ``(phase, done, total, figures)``; phases "windows", "train".
    Returns:
        the result and the notes for the user.
    Raises:
        InputError / WeightsError: bad inputs or weights.
    """
    from ..models.weights import default_weights_path, load_weights, weights_hash

    config = FinetuneConfig() if config is None else config
    started = time.perf_counter()
    if threads is not None:
        if threads < 1:
            raise InputError(f"threads must be ≥ 1, got {threads}")
        torch.set_num_threads(threads)
    model, meta = load_weights(weights, device="cpu")
    if model.channels != 1:
        raise InputError("fine-tuning takes gray weights (channels = 1)",
                         hint="fine-tune gray weights: events carry no colour")
    _check_parts(model, config.trainable)  # before minutes of reading windows
    groups = input_groups(inputs)
    say = progress or (lambda *a: None)
    windows, notes = prepare_windows(groups, model.n, timing=model.needs.timing,
                                     config=config, read_options=read_options,
                                     exposure=exposure, offset_us=offset_us,
                                     on_window=lambda d, t: say("windows", d, t, {}))
    train, held = split_windows(windows, config.holdout)
    trusted = sum(w.trusted for w in train)
    if trusted == 0 and any(config.losses.get(k, 0) > 0 for k in MOTION_TERMS):
        why = (f"no training window shows a reliable motion (contrast gain ≥ "
               f"{config.min_confidence:g}, and re-blurring along it explains the blurry frame "
               "somewhere)")
        others = [k for k, w in config.losses.items() if w > 0 and k not in MOTION_TERMS]
        if not others:
            # minutes of steps that move no weight would end in the starting weights
            raise InputError(f"nothing to fine-tune on: {why}",
                             path=groups[0][0] if groups and groups[0] else None,
                             hint="give recordings where the camera moves over a still scene, "
                             "or turn on --loss event_consistency=…")
        notes.append(f"{why}: only {', '.join(others)} train")

    model.eval()
    before = held_out_losses(model, held, config) if held else {}
    example_before = _middle(model, held[0]) if held else None

    tune(model, train, config, progress=say)
    model.eval()
    after = held_out_losses(model, held, config) if held else {}
    example = None
    if held:
        example = (held[0].name, held[0].blurry, example_before, _middle(model, held[0]))

    path = default_weights_path() if weights is None else Path(weights)
    record = {
        "inputs": [Path(p).name for g in groups for p in g],
        "init_weights": weights_hash(path),
        "windows": len(train), "held_out": len(held), "trusted_motion": trusted,
        "steps": config.steps, "crop": config.crop, "batch_size": config.batch_size,
        "lr": config.lr, "losses": dict(config.losses), "anchor": config.anchor,
        "contrast": config.contrast, "held_out_before": before, "held_out_after": after,
    }
    # what the starting weights were trained on stays true; their figures are not these
    # weights' figures
    new_meta = {k: v for k, v in meta.items() if k in ("recipe", "training_data", "description",
                                                        "architecture")}
    new_meta["finetune"] = record
    result = FinetuneResult(model, new_meta, len(train), len(held), trusted, before, after,
                            time.perf_counter() - started, example)
    return result, notes

