"""The training loop: recipe + data → weights, a CSV log, a curve, resumable checkpoints.

``train()`` never prints; it reports through a :class:`Reporter` (the CLI draws a progress bar
from it) and raises :class:`~trmd_cli.errors.TrmdError` subclasses on bad input.

RUN_DIR receives (rank 0 only, all atomically):

- ``checkpoint.safetensors``: everything needed to resume (see :mod:`.checkpoint`);
- ``log.csv``: step, epoch, loss, lr, val_psnr_mid, val_psnr_seq, seconds;
- ``curve.png``: loss and validation PSNR against step;
- ``best.safetensors``: weights with the best validation PSNR of the middle frame so far;
- ``final.safetensors``: weights at the end (all steps done or the time budget used up);
- ``recipe.json``: the resolved recipe and data of the run.

Reproducibility: every random choice is seeded from the recipe (model init from ``seed``, sample
order and crops from (seed, epoch, index)), and checkpoints hold the RNG states, optimiser and
log, so an interrupted run resumed with ``resume=True`` ends with the weights an uninterrupted
run would have produced (to floating-point tolerance).
"""

from __future__ import annotations

import contextlib
import csv
import io
import math
import os
import random
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from ..errors import InputError, OutputExistsError, TrmdError, WeightsError
from ..precision import autocast, precision_name, resolve_precision
from . import ddp
from .checkpoint import load_checkpoint, read_checkpoint_state, save_checkpoint
from .data import DataPlan, EpochSampler, build_data, set_epoch
from .ema import WeightAverage
from .losses import SUPERVISED, total_loss
from .recipe import (
    RESUME_LENGTH_KEYS,
    RESUME_SAFE_KEYS,
    Recipe,
    apply_overrides,
    load_recipe,
    recipe_diff,
    recipe_from_dict,
)

__all__ = ["train", "TrainResult", "Reporter", "lr_at", "evaluate", "LOG_COLUMNS",
           "CHECKPOINT", "RUN_FILES", "build_model"]

CHECKPOINT = "checkpoint.safetensors"
#: every file a run writes into its folder
RUN_FILES = (CHECKPOINT, "log.csv", "curve.png", "best.safetensors", "final.safetensors",
             "recipe.json")
LOG_COLUMNS = ("step", "epoch", "loss", "lr", "val_psnr_mid", "val_psnr_seq", "seconds")


class Reporter(Protocol):
    """What the loop tells its caller. All methods are optional to act upon."""

    def start(self, *, total: int, done: int, info: dict[str, Any]) -> None: ...
    def step(self, *, step: int, loss: float, lr: float) -> None: ...
    def validated(self, *, step: int, psnr_mid: float, psnr_seq: float) -> None: ...
    def note(self, message: str) -> None: ...
    def close(self) -> None: ...


class _Silent:
    def start(self, **_: Any) -> None: ...
    def step(self, **_: Any) -> None: ...
    def validated(self, **_: Any) -> None: ...
    def note(self, message: str) -> None: ...
    def close(self) -> None: ...


@dataclass
class TrainResult:
    """How a run ended. PSNRs in dB (None without a validation set); seconds of training."""

    run_dir: Path
    steps: int
    total_steps: int
    epochs: float
    seconds: float
    stopped: str  # "done", "time_budget" or "session_limit"
    val_psnr_mid: float | None
    val_psnr_seq: float | None
    best_val_psnr_mid: float | None
    best_step: int | None
    final_weights: Path | None
    best_weights: Path | None
    notes: list[str] = field(default_factory=list)


def lr_at(step: int, recipe: Recipe, total: int) -> float:
    """Learning rate for optimiser step ``step`` (0-based) of ``total``.

    Linear warm-up from lr/warmup to lr over ``warmup_steps``, then constant or cosine decay
    to ``min_lr`` at the last step.
    """
    o = recipe.optim
    if o.warmup_steps and step < o.warmup_steps:
        return o.lr * (step + 1) / o.warmup_steps
    if o.schedule == "constant":
        return o.lr
    span = max(total - o.warmup_steps, 1)
    frac = min(max((step - o.warmup_steps) / span, 0.0), 1.0)
    return o.min_lr + 0.5 * (o.lr - o.min_lr) * (1.0 + math.cos(math.pi * frac))


def build_model(recipe: Recipe) -> torch.nn.Module:
    """``create_model(model.name, n=…, channels=…, **model.args)``, with recipe-named errors."""
    from ..models import create_model

    m = recipe.model
    try:
        return create_model(m.name, n=m.n, channels=m.channels, **m.args)
    except TypeError as e:
        raise InputError(f"model.args do not fit model {m.name!r}: {e}",
                         hint="check the keys of [model.args]") from None


def forward(model: torch.nn.Module, batch: dict[str, torch.Tensor], *, needs_contrast: bool,
            jitter: float = 0.0, fallback_contrast: float = 0.2,
            timing: bool = False) -> torch.Tensor:
    """The network's residuals for a batch; networks that take the threshold c get the batch's
    true c (``fallback_contrast`` where unknown) times ``exp(N(0, jitter))``; networks that take
    sub-bin timing (``timing``) get ``batch["levels"]`` after the voxels (the counts again
    where the data has none, as in use on binned data)."""
    voxels = batch["voxels"]
    if timing:
        voxels = torch.cat([voxels, batch.get("levels", voxels)], 1)
    if not needs_contrast:
        return model(batch["blurry"], voxels)
    c = batch["contrast"].to(batch["blurry"].device, torch.float32).reshape(-1)
    c = torch.where(torch.isfinite(c) & (c > 0), c, torch.full_like(c, fallback_contrast))
    if jitter > 0:
        c = c * torch.exp(jitter * torch.randn(c.shape)).to(c.device)
    return model(batch["blurry"], voxels, c)


def _has_true_contrast(dataset) -> bool:
    """Whether samples carry their sensor's threshold (judged by the first one)."""
    c = dataset[0].get("contrast") if len(dataset) else None
    return c is not None and bool(torch.isfinite(torch.as_tensor(c)).all())


def _to_device(batch: dict[str, torch.Tensor], device: torch.device,
               channels_last: bool) -> dict[str, torch.Tensor]:
    out = {}
    for k, v in batch.items():
        v = v.to(device, non_blocking=True)
        if channels_last and v.ndim == 4:
            v = v.contiguous(memory_format=torch.channels_last)
        out[k] = v
    return out


@torch.no_grad()
def evaluate(model: torch.nn.Module, dataset, *, dist: ddp.Dist | None = None,
             batch_size: int = 1, amp_dtype: torch.dtype | None = None,
             fallback_contrast: float = 0.2) -> tuple[float, float, int]:
    """Mean validation PSNR (dB, data range 1, outputs clipped to [0, 1]) over ``dataset``.

    Networks that take the threshold c get each sample's true c (``fallback_contrast`` where
    the data has none) — in use they get an estimate, so this is slightly optimistic for them.
    ``amp_dtype``: autocast dtype of the network (None = float32; see :mod:`trmd_cli.precision`).

    Returns:
        (middle-frame PSNR, sequence PSNR = mean of the per-frame PSNRs, sample count); each
        averaged over samples. Under DDP the samples are shared among processes and the sums
        gathered, so every process gets the same figures.
    """
    from ..metrics import psnr_per_item
    from ..reconstruct import reconstruct

    dist = dist or ddp.Dist()
    device = dist.device
    was_training = model.training
    model.eval()
    idx = list(range(dist.rank, len(dataset), dist.world))
    s_mid = s_seq = 0.0
    count = 0
    try:
        for start in range(0, len(idx), batch_size):
            items = [dataset[i] for i in idx[start:start + batch_size]]
            batch = {k: torch.stack([it[k] for it in items]).to(device) for k in
                     ("blurry", "voxels", "levels", "sharp", "contrast") if k in items[0]}
            with autocast(device, amp_dtype):
                residuals = forward(model, batch, fallback_contrast=fallback_contrast,
                                    needs_contrast=getattr(model, "needs_contrast", False),
                                    timing=bool(getattr(model, "timing", False)))
            latent = reconstruct(batch["blurry"], residuals.float()).clamp(0.0, 1.0)
            sharp = batch["sharp"]
            b, frames = sharp.shape[:2]
            mid = frames // 2
            s_mid += float(psnr_per_item(latent[:, mid], sharp[:, mid]).sum())
            per_frame = psnr_per_item(latent.flatten(0, 1), sharp.flatten(0, 1)).view(b, frames)
            s_seq += float(per_frame.mean(1).sum())
            count += b
    finally:
        model.train(was_training)
    s_mid, s_seq, total = ddp.all_reduce_sum(dist, [s_mid, s_seq, float(count)])
    if total == 0:
        return float("nan"), float("nan"), 0
    return s_mid / total, s_seq / total, int(total)


def _write_log(path: Path, history: Sequence[dict]) -> None:
    from ..write import write_text

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(LOG_COLUMNS)
    for row in history:
        out = []
        for col in LOG_COLUMNS:
            v = row.get(col)
            if v is None:
                out.append("")
            elif col == "step":
                out.append(str(int(v)))
            elif col == "lr":
                out.append(f"{v:.6g}")
            else:
                out.append(f"{v:.6f}" if isinstance(v, float) else str(v))
        w.writerow(out)
    write_text(path, buf.getvalue())


def _threads(recipe: Recipe, dist: ddp.Dist) -> int:
    if recipe.train.threads:
        return recipe.train.threads
    local = int(os.environ.get("LOCAL_WORLD_SIZE", dist.world) or 1)
    return max(1, (os.cpu_count() or 1) // max(local, 1))


def _seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    torch.manual_seed(seed)


def _make_optimizer(model: torch.nn.Module, recipe: Recipe) -> torch.optim.Optimizer:
    o = recipe.optim
    cls = torch.optim.AdamW if o.name == "adamw" else torch.optim.Adam
    # foreach=False: the same arithmetic whatever the tensor layout, for exact resumes
    return cls(model.parameters(), lr=o.lr, betas=o.betas, weight_decay=o.weight_decay,
               foreach=False)


def _resolve_run(data: Sequence[str | Path] | None, recipe: Recipe | None, run_dir: Path,
                 resume: bool, overrides: list[str] | None
                 ) -> tuple[Recipe, list[str], dict | None, list[str]]:
    """Recipe and data for a new or resumed run, checked against the checkpoint."""
    notes: list[str] = []
    ckpt = run_dir / CHECKPOINT
    if not resume:
        recipe = recipe or load_recipe(None)
        if overrides:
            recipe = apply_overrides(recipe, overrides)
        return recipe, [str(Path(p).expanduser().resolve()) for p in (data or [])], None, notes
    state = read_checkpoint_state(ckpt)
    stored = recipe_from_dict(state["recipe"], source=ckpt,
                              base_dir=state.get("recipe_base_dir") or None)
    recipe = recipe or stored
    if overrides:
        recipe = apply_overrides(recipe, overrides)
    diff = recipe_diff(stored, recipe)
    changed = [k for k in diff if k not in RESUME_SAFE_KEYS | RESUME_LENGTH_KEYS]
    if changed:
        raise InputError(f"the recipe differs from the one the run started with in "
                         f"{', '.join(changed)}", path=ckpt,
                         hint="resume with the run's own recipe (omit --recipe), or start a new "
                         "run (--init-weights to fine-tune from its weights)")
    if any(k in RESUME_LENGTH_KEYS for k in diff):
        notes.append("the run's length changed: the learning-rate schedule differs from the "
                     "original run's from here on")
    stored_data = list(state.get("data") or [])
    new_data = [str(Path(p).expanduser().resolve()) for p in (data or [])]
    if new_data and new_data != stored_data:
        raise InputError("--data differs from the data the run started with", path=ckpt,
                         hint="omit --data when resuming (the run's own data is used)")
    return recipe, stored_data, state, notes


def train(data: Sequence[str | Path] | None = None, *, recipe: Recipe | None = None,
          run_dir: str | Path, resume: bool = False, init_weights: str | Path | None = None,
          overrides: list[str] | None = None, overwrite: bool = False, device: str = "auto",
          reporter: Reporter | None = None,
          session_steps: int | None = None,
          clock: Callable[[], float] = time.monotonic) -> TrainResult:
    """Train a RE-Net as ``recipe`` says on ``data``, writing into ``run_dir``.

    Args:
        data: ``--data`` paths (image folders, trmd HDF5 sets, GOPRO-layout h5); may be None
            when resuming (the run's own data is used).
        recipe: None = the shipped default (or, when resuming, the run's own recipe).
        run_dir: output folder; created if missing.
        resume: continue from ``run_dir/checkpoint.safetensors``.
        init_weights: a weights file (``save_weights`` format) or another run's
            ``checkpoint.safetensors`` to start from (fine-tuning; only the weights are taken).
        overrides: ``"section.key=value"`` changes to the recipe (on resume only keys in
            :data:`~.recipe.RESUME_SAFE_KEYS` may change).
        overwrite: start afresh in a ``run_dir`` that already holds a run.
        device: ``"auto"``, ``"cpu"`` or ``"cuda"``.
        reporter: receives progress; the loop itself never prints.
        session_steps: stop (checkpointed, resumable) after this many steps in this call.
        clock: seconds, monotonic; the time budget is measured with it.
    Returns:
        :class:`TrainResult`.
    Raises:
        InputError, FormatError, WeightsError, OutputExistsError: with what to do about it.
    """
    t_start = clock()  # the time budget counts from here: setup and data loading included
    reporter = reporter or _Silent()
    run_dir = Path(run_dir).expanduser()
    if not resume and (run_dir / CHECKPOINT).exists() and not overwrite:
        raise OutputExistsError("this folder already holds a training run", path=run_dir,
                                hint="pass --resume to continue it, --overwrite to start over, "
                                "or choose another --out")
    if resume and init_weights is not None:
        raise InputError("--init-weights cannot be combined with --resume",
                         hint="a resumed run continues from its own checkpoint")
    recipe, data_paths, resumed, notes = _resolve_run(data, recipe, run_dir, resume,
                                                      overrides)
    if not data_paths:
        raise InputError("no training data given", hint="pass --data FOLDER_OR_H5")

    dist = ddp.setup(device)
    try:
        return _train(recipe, data_paths, run_dir, resumed, init_weights, dist, reporter,
                      session_steps, clock, t_start, notes)
    finally:
        ddp.teardown(dist)


def _train(recipe: Recipe, data_paths: list[str], run_dir: Path, resumed: dict | None,
           init_weights: str | Path | None, dist: ddp.Dist, reporter: Reporter,
           session_steps: int | None, clock: Callable[[], float], t_start: float,
           notes: list[str]) -> TrainResult:
    from ..reconstruct import reconstruct

    r, tr = recipe, recipe.train
    torch.set_num_threads(_threads(recipe, dist))
    _seed_everything(r.seed)
    supervised = any(w > 0 for k, w in r.loss.weights.items() if k in SUPERVISED)
    plan: DataPlan = build_data(data_paths, r, supervised=supervised)
    notes += plan.notes
    batch = r.data.batch_size
    per_rank = len(plan.train) // dist.world
    bpe = per_rank // batch
    if bpe < 1:
        raise InputError(f"{len(plan.train)} training sample(s) make no full batch of {batch} "
                         f"per process ({dist.world} process(es))",
                         hint="lower data.batch_size or add data (data.length for image folders)")
    total = tr.epochs * bpe if tr.epochs else tr.steps

    model = build_model(r).to(dist.device)
    if tr.channels_last:
        model = model.to(memory_format=torch.channels_last)
    optimizer = _make_optimizer(model, r)
    # on resume the checkpoint's average replaces this copy; otherwise it starts from the
    # initial weights, so it is made only after --init-weights is loaded
    ema = WeightAverage(model, r.optim.ema) if r.optim.ema > 0 and resumed is not None else None
    # mixed precision where the hardware runs it natively: float16 on CUDA (with loss
    # scaling), bfloat16 on CPUs with AMX / AVX512-BF16 (same range as float32: no scaling)
    amp_dtype = resolve_precision("auto" if tr.amp else "fp32", dist.device)
    scaler = torch.amp.GradScaler("cuda") if amp_dtype == torch.float16 else None
    # validation stays in float32 on CPU so figures compare across runs and machines
    val_dtype = amp_dtype if dist.device.type == "cuda" else None

    step, seconds_before = 0, 0.0
    history: list[dict] = []
    best: dict[str, Any] = {"psnr_mid": None, "psnr_seq": None, "step": None}
    last_val: dict[str, Any] = {"psnr_mid": None, "psnr_seq": None, "step": None}
    acc = [0.0, 0]  # running loss sum and count since the last log row
    if resumed is not None:
        doc = load_checkpoint(run_dir / CHECKPOINT, model=model, optimizer=optimizer,
                              scaler=scaler, ema=ema)
        step, seconds_before = int(doc["step"]), float(doc["seconds"])
        history, best, last_val = doc["history"], doc["best"], doc["last_val"]
        acc = list(doc["loss_acc"])
        if int(doc.get("world", 1)) != dist.world:
            notes.append(f"resumed with {dist.world} process(es), the run started with "
                         f"{doc.get('world')}: the batches differ from an uninterrupted run")
    elif init_weights is not None:
        grown = _load_init(model, init_weights, r)
        timing_in = getattr(model, "TIMING_INPUTS", ())
        # the feature extractors' first convs: the head also grows with a wider U-Net
        timed = [k for k in grown if k in timing_in[:2]]
        # a wider U-Net lists all its layers as grown (down1 is never grown otherwise)
        wider = "down1.0.weight" in grown
        added = [] if wider else sorted({k.split(".")[0] for k in grown if k not in timing_in})
        if added:
            notes.append(f"--init-weights had no {', '.join(added)} layers: they start as an "
                         "identity, so the run starts from exactly what those weights computed")
        if timed:
            notes.append("--init-weights had no timing inputs: their weights start at zero, "
                         "so the run starts from exactly what those weights computed")
        if wider:
            notes.append("--init-weights has a narrower U-Net: the new channels start random, "
                         "their weights into the old ones at zero, so the run starts from "
                         "exactly what those weights computed")
    if ema is None and r.optim.ema > 0:
        ema = WeightAverage(model, r.optim.ema)

    bare = model
    needs_contrast = bool(getattr(bare, "needs_contrast", False))
    if needs_contrast and not _has_true_contrast(plan.train):
        notes.append(f"the training data stores no true contrast threshold: "
                     f"{r.model.name} is given loss.contrast = {r.loss.contrast} "
                     "(set it to your camera's, or train a network without it)")
    # what is validated and written as best/final weights: the average when there is one
    judged = ema.module if ema is not None else bare
    if dist.enabled:
        model = torch.nn.parallel.DistributedDataParallel(
            bare, device_ids=[dist.device.index] if dist.device.type == "cuda" else None)
    if dist.is_main:
        run_dir.mkdir(parents=True, exist_ok=True)
        if resumed is None:  # a fresh start: no stale outputs of an earlier run stay behind
            for name in RUN_FILES:
                (run_dir / name).unlink(missing_ok=True)
        for name in RUN_FILES:  # temporaries of a process killed (-9) while writing
            stem = Path(name).stem
            for tmp in run_dir.glob(f".{stem}.*.tmp*"):
                tmp.unlink(missing_ok=True)
        from ..write import write_json

        write_json(run_dir / "recipe.json", {"recipe": r.to_dict(), "data": data_paths,
                                             "validation": plan.val_source, "world": dist.world})

    sampler = EpochSampler(len(plan.train), seed=r.seed, rank=dist.rank, world=dist.world)
    budget = tr.time_budget_minutes * 60.0
    t0 = t_start
    last_ckpt = clock()
    step_time = 0.0
    val_time = ckpt_time = 0.0
    stopped = "done"
    start_step = step
    final_path = best_path = None

    def elapsed() -> float:
        return seconds_before + (clock() - t0)

    def validate() -> None:
        nonlocal val_time
        if plan.val is None:
            return
        tv = clock()
        vb = r.data.batch_size if r.data.val_crop else 1
        mid, seq, _ = evaluate(judged, plan.val, dist=dist, batch_size=vb, amp_dtype=val_dtype,
                               fallback_contrast=r.loss.contrast)
        val_time = clock() - tv
        last_val.update(psnr_mid=mid, psnr_seq=seq, step=step)
        reporter.validated(step=step, psnr_mid=mid, psnr_seq=seq)
        if best["psnr_mid"] is None or mid > best["psnr_mid"]:
            best.update(psnr_mid=mid, psnr_seq=seq, step=step)
            if dist.is_main:
                nonlocal best_path
                best_path = _save_weights(run_dir / "best.safetensors", judged, r, data_paths,
                                          plan, step, total, bpe, elapsed(), last_val, best)

    def row(loss: float | None, lr: float, val: bool) -> None:
        entry: dict[str, Any] = {"step": step, "epoch": step / bpe, "loss": loss, "lr": lr,
                                 "val_psnr_mid": last_val["psnr_mid"] if val else None,
                                 "val_psnr_seq": last_val["psnr_seq"] if val else None,
                                 "seconds": elapsed()}
        if history and history[-1]["step"] == step:
            history[-1].update({k: v for k, v in entry.items() if v is not None})
        else:
            history.append(entry)

    def save() -> None:
        nonlocal last_ckpt, ckpt_time
        tc = clock()
        if dist.is_main:
            save_checkpoint(run_dir / CHECKPOINT, model=bare, optimizer=optimizer, scaler=scaler,
                            ema=ema,
                            state={"step": step, "total_steps": total, "epoch": step // bpe,
                                   "skip": (step % bpe) * batch, "batches_per_epoch": bpe,
                                   "seconds": elapsed(), "history": history, "best": best,
                                   "last_val": last_val, "loss_acc": acc,
                                   "recipe": r.to_dict(), "recipe_base_dir": r.base_dir,
                                   "data": data_paths, "world": dist.world})
            _write_outputs(run_dir, history, r.name)
        ddp.barrier(dist)
        last_ckpt = clock()
        ckpt_time = last_ckpt - tc

    reporter.start(total=total, done=step, info={
        "run_dir": str(run_dir), "recipe": r.name, "model": r.model.name,
        "train": plan.sources, "validation": plan.val_source, "batches_per_epoch": bpe,
        "world": dist.world, "device": str(dist.device), "threads": torch.get_num_threads(),
        "precision": precision_name(amp_dtype),
        "resumed_at": step if resumed is not None else None})
    for note in notes:
        reporter.note(note)

    if budget and seconds_before >= budget and step < total:
        stopped = "time_budget"  # resumed with the budget already used up: no extra step
    try:
        while step < total and stopped == "done":
            epoch = step // bpe
            set_epoch(plan.train, epoch)
            sampler.set_position(epoch, (step % bpe) * batch)
            loader = torch.utils.data.DataLoader(
                plan.train, batch_size=batch, sampler=sampler, drop_last=True,
                num_workers=r.data.num_workers, pin_memory=dist.device.type == "cuda",
                # a private generator: creating the iterator must not draw from the global RNG
                generator=torch.Generator().manual_seed(r.seed * 1000003 + epoch))
            for raw in loader:
                ts = clock()
                lr = lr_at(step, r, total)
                for g in optimizer.param_groups:
                    g["lr"] = lr
                b = _to_device(raw, dist.device, tr.channels_last)
                with autocast(dist.device, amp_dtype):
                    residuals = forward(model, b, needs_contrast=needs_contrast,
                                        jitter=r.data.contrast_jitter,
                                        fallback_contrast=r.loss.contrast,
                                        timing=bool(getattr(bare, "timing", False)))
                residuals = residuals.float()
                outputs = {"residuals": residuals, "latent": reconstruct(b["blurry"], residuals)}
                loss, _ = total_loss(outputs, b, r)
                optimizer.zero_grad(set_to_none=True)
                if scaler is not None:
                    scaler.scale(loss).backward()
                    scaler.unscale_(optimizer)
                else:
                    loss.backward()
                if r.optim.grad_clip > 0:
                    torch.nn.utils.clip_grad_norm_(bare.parameters(), r.optim.grad_clip)
                if scaler is not None:
                    scaler.step(optimizer)
                    scaler.update()
                else:
                    optimizer.step()
                if ema is not None:
                    ema.update(bare)
                value = float(loss.detach())
                if not math.isfinite(value) and scaler is None:
                    raise TrmdError(f"training diverged at step {step + 1} (loss {value})",
                                    hint="lower optim.lr or raise optim.warmup_steps")
                step += 1
                acc[0] += value
                acc[1] += 1
                step_time = clock() - ts
                reporter.step(step=step, loss=value, lr=lr)

                logged = step % tr.log_every == 0 or step == total
                if logged:
                    s, n = ddp.all_reduce_sum(dist, [acc[0], float(acc[1])])
                    row(s / max(n, 1), lr, False)
                    acc[:] = [0.0, 0]
                if step % tr.val_every == 0 or step == total:
                    validate()
                    row(None, lr, True)
                # stop while one more step, a validation and two saves still fit the budget;
                # every process must agree, so the clocks' verdicts are summed over processes
                out_of_time = bool(budget) and (
                    elapsed() + step_time + val_time + 2 * ckpt_time + 1.0 >= budget)
                due = bool(tr.checkpoint_minutes) and (
                    clock() - last_ckpt >= tr.checkpoint_minutes * 60)
                out_of_time, timed = (v > 0 for v in ddp.all_reduce_sum(
                    dist, [float(out_of_time), float(due)]))
                if out_of_time and step < total:
                    stopped = "time_budget"
                session_over = session_steps is not None and step - start_step >= session_steps
                if session_over and stopped == "done" and step < total:
                    stopped = "session_limit"
                if stopped == "time_budget" and last_val["step"] != step:
                    validate()
                    row(None, lr, True)
                if (step % tr.checkpoint_every == 0 or timed or step == total
                        or stopped != "done"):
                    save()
                elif logged and dist.is_main:
                    _write_outputs(run_dir, history, r.name)
                if stopped != "done" or step >= total:
                    break
    finally:
        reporter.close()

    if stopped in ("done", "time_budget") and dist.is_main:
        final_path = _save_weights(run_dir / "final.safetensors", judged, r, data_paths, plan,
                                   step, total, bpe, elapsed(), last_val, best)
        if best_path is None and (run_dir / "best.safetensors").exists():
            best_path = run_dir / "best.safetensors"
    ddp.barrier(dist)
    return TrainResult(run_dir=run_dir, steps=step, total_steps=total, epochs=step / bpe,
                       seconds=elapsed(), stopped=stopped, val_psnr_mid=last_val["psnr_mid"],
                       val_psnr_seq=last_val["psnr_seq"], best_val_psnr_mid=best["psnr_mid"],
                       best_step=best["step"], final_weights=final_path, best_weights=best_path,
                       notes=notes)


def _write_outputs(run_dir: Path, history: Sequence[dict], title: str) -> None:
    from .plots import write_curve

    _write_log(run_dir / "log.csv", history)
    write_curve(run_dir / "curve.png", history, title=title)


def _load_init(model: torch.nn.Module, path: str | Path, recipe: Recipe) -> list[str]:
    """Start from a weights file, or from the weights in another run's checkpoint; the names
    of layers the weights lacked and that start as an identity (:func:`load_init_state`)."""
    from ..weights import load_weights
    from .checkpoint import is_checkpoint, load_checkpoint_weights, load_init_state

    if is_checkpoint(path):
        return list(load_checkpoint_weights(path, model).get("grown", []))

    src, meta = load_weights(path, expect_n=recipe.model.n,
                             expect_channels=recipe.model.channels)
    try:
        return load_init_state(model, src.state_dict())
    except RuntimeError as e:
        raise WeightsError(f"weights do not fit model {recipe.model.name!r} "
                           f"({str(e).splitlines()[0]})", path=path,
                           hint=f"they are for {meta.get('architecture')}: set model.name and "
                           "model.args to match") from None


def _save_weights(path: Path, model: torch.nn.Module, recipe: Recipe, data: list[str],
                  plan: DataPlan, step: int, total: int, bpe: int, seconds: float,
                  last_val: dict, best: dict) -> Path:
    from ..weights import save_weights

    figures = {"steps": step, "total_steps": total, "epochs": step / bpe,
               "train_seconds": round(seconds, 1),
               "val_psnr_mid": last_val["psnr_mid"], "val_psnr_seq": last_val["psnr_seq"],
               "val_step": last_val["step"], "best_val_psnr_mid": best["psnr_mid"],
               "best_step": best["step"], "validation": plan.val_source}
    meta = {"recipe": recipe.to_dict(), "figures": figures,
            "training_data": [Path(p).name for p in data]}
    with contextlib.suppress(AttributeError):
        if not getattr(model, "variant", None):
            model.variant = recipe.model.name
    return save_weights(path, model, meta=meta)
