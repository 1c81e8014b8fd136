"""What one training run does, one piece at a time: a step, a validation, a checkpoint.

:class:`Run` holds what stays fixed while a run goes (recipe, data, the network and its
optimiser, where the outputs go); :class:`TrainState` holds what changes and what checkpoints
carry besides tensors. :func:`step`, :func:`validate` and :func:`checkpoint` advance the state;
:mod:`.loop` decides when each happens.

Metadata written here names the validation set by its file name and SHA-256
(:func:`~.data.data_record`), never by a path on the training machine; the checkpoint keeps
the path, since resuming reads the set again.
"""

from __future__ import annotations

import contextlib
import csv
import io
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from ..errors import TrmdError
from ..models.inputs import RENetInputs, RENetNeeds
from ..precision import autocast
from . import ddp
from .checkpoint import save_checkpoint
from .data import DataPlan
from .ema import WeightAverage
from .losses import total_loss
from .recipe import Recipe

if TYPE_CHECKING:
    from ..models.renet import RENet

__all__ = ["CHECKPOINT", "LOG_COLUMNS", "Run", "TrainState", "lr_at", "forward", "evaluate",
           "step", "validate", "checkpoint", "write_outputs", "save_run_weights",
           "recipe_record"]

CHECKPOINT = "checkpoint.safetensors"
LOG_COLUMNS = ("step", "epoch", "loss", "lr", "val_psnr_mid", "val_psnr_seq", "seconds")


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


def forward(model: torch.nn.Module, batch: dict[str, torch.Tensor], *, needs: RENetNeeds,
            jitter: float = 0.0, fallback_contrast: float = 0.2) -> torch.Tensor:
    """The network's residuals for a batch (:class:`~trmd_cli.models.RENetInputs` from it).

    Networks that take the threshold c (``needs.contrast``) get the batch's true c
    (``fallback_contrast`` where unknown) times ``exp(N(0, jitter))``, drawn from torch's
    global generator; networks that take the sub-bin timing (``needs.timing``) get
    ``batch["levels"]``, or the counts again where the data has none, as in use on binned data.
    """
    voxels = batch["voxels"]
    levels = batch.get("levels", voxels) if needs.timing else None
    if not needs.contrast:
        return model(RENetInputs(batch["blurry"], voxels, levels=levels))
    c = batch["contrast"].to(batch["blurry"].device, torch.float32).reshape(-1)
    c = torch.where(torch.isfinite(c) & (c > 0), c, torch.full_like(c, fallback_contrast))
    if jitter > 0:
        c = c * torch.exp(jitter * torch.randn(c.shape)).to(c.device)
    return model(RENetInputs(batch["blurry"], voxels, levels=levels, contrast=c))


@torch.no_grad()
def evaluate(model: torch.nn.Module, dataset, *, dist: ddp.Dist | None = None,
             batch_size: int = 1, amp_dtype: torch.dtype | None = None,
             fallback_contrast: float = 0.2) -> tuple[float, float, int]:
    """Mean validation PSNR (dB, data range 1, outputs clipped to [0, 1]) over ``dataset``.

    ``model`` is a RE-Net (it says what it takes: ``model.needs``). Networks that take the
    threshold c get each sample's true c (``fallback_contrast`` where the data has none) — in
    use they get an estimate, so this is slightly optimistic for them. ``amp_dtype``: autocast
    dtype of the network (None = float32; see :mod:`trmd_cli.precision`).

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
                residuals = forward(model, batch, needs=model.needs,
                                    fallback_contrast=fallback_contrast)
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


# --------------------------------------------------------------------------------------------
# A run and its state


def _no_figures() -> dict[str, Any]:
    return {"psnr_mid": None, "psnr_seq": None, "step": None}


@dataclass
class TrainState:
    """What changes as a run goes.

    Checkpointed (:meth:`from_checkpoint`): ``step`` (optimiser steps done), ``seconds_before``
    (training seconds of earlier calls of :func:`~.loop.train` on the run), ``history`` (log
    rows), ``best`` and ``last_val`` (``psnr_mid``, ``psnr_seq`` in dB and their ``step``),
    ``loss_acc`` (loss sum and count since the last log row). Of this call only, in seconds of
    the run's clock: how long the last step, validation and checkpoint took, and when the last
    checkpoint was written; ``best_path``, the best weights written by this call.
    """

    step: int = 0
    seconds_before: float = 0.0
    history: list[dict[str, Any]] = field(default_factory=list)
    best: dict[str, Any] = field(default_factory=_no_figures)
    last_val: dict[str, Any] = field(default_factory=_no_figures)
    loss_acc: list = field(default_factory=lambda: [0.0, 0])
    step_time: float = 0.0
    val_time: float = 0.0
    ckpt_time: float = 0.0
    last_ckpt: float = 0.0
    best_path: Path | None = None

    @classmethod
    def from_checkpoint(cls, doc: dict[str, Any]) -> TrainState:
        """The state a checkpoint's JSON document (:func:`~.checkpoint.load_checkpoint`)
        holds."""
        return cls(step=int(doc["step"]), seconds_before=float(doc["seconds"]),
                   history=doc["history"], best=doc["best"], last_val=doc["last_val"],
                   loss_acc=list(doc["loss_acc"]))


@dataclass(frozen=True, eq=False)
class Run:
    """What stays fixed while a run goes.

    Attributes:
        model: what is trained: ``bare``, or its DistributedDataParallel wrapper.
        bare: the RE-Net itself (checkpointed, clipped, averaged).
        total: optimiser steps of the whole run; ``bpe``: batches per epoch and process.
        data_paths: the training data as given (absolute paths, for resuming).
        val_dtype: autocast dtype of validation (None = float32).
        t0: the clock when this call of :func:`~.loop.train` started; ``clock`` measures
            seconds.
    """

    recipe: Recipe
    plan: DataPlan
    data_paths: list[str]
    run_dir: Path
    dist: ddp.Dist
    model: torch.nn.Module
    bare: RENet
    optimizer: torch.optim.Optimizer
    scaler: Any
    ema: WeightAverage | None
    amp_dtype: torch.dtype | None
    val_dtype: torch.dtype | None
    total: int
    bpe: int
    reporter: Any
    clock: Callable[[], float]
    t0: float

    @property
    def judged(self) -> RENet:
        """What is validated and written as best/final weights: the average when there is one."""
        return self.ema.module if self.ema is not None else self.bare

    def elapsed(self, state: TrainState) -> float:
        """Training seconds of the whole run so far, earlier calls included."""
        return state.seconds_before + (self.clock() - self.t0)


def _to_device(batch: dict[str, torch.Tensor], device: torch.device,
               channels_last: bool) -> dict[str, torch.Tensor]:
    out = {}
    for k, v in batch.items():
        v = v.to(device, non_blocking=True)
        if channels_last and v.ndim == 4:
            v = v.contiguous(memory_format=torch.channels_last)
        out[k] = v
    return out


def step(run: Run, state: TrainState, raw: dict[str, torch.Tensor]) -> tuple[float, float]:
    """One optimiser step on a batch from the loader; returns (loss, learning rate).

    Raises:
        TrmdError: the loss is not finite (without loss scaling, which skips such steps).
    """
    from ..reconstruct import reconstruct

    r, optimizer, scaler = run.recipe, run.optimizer, run.scaler
    ts = run.clock()
    lr = lr_at(state.step, r, run.total)
    for g in optimizer.param_groups:
        g["lr"] = lr
    b = _to_device(raw, run.dist.device, r.train.channels_last)
    with autocast(run.dist.device, run.amp_dtype):
        residuals = forward(run.model, b, needs=run.bare.needs, jitter=r.data.contrast_jitter,
                            fallback_contrast=r.loss.contrast)
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
        torch.nn.utils.clip_grad_norm_(run.bare.parameters(), r.optim.grad_clip)
    if scaler is not None:
        scaler.step(optimizer)
        scaler.update()
    else:
        optimizer.step()
    if run.ema is not None:
        run.ema.update(run.bare)
    value = float(loss.detach())
    if not math.isfinite(value) and scaler is None:
        raise TrmdError(f"training diverged at step {state.step + 1} (loss {value})",
                        hint="lower optim.lr or raise optim.warmup_steps")
    state.step += 1
    state.loss_acc[0] += value
    state.loss_acc[1] += 1
    state.step_time = run.clock() - ts
    run.reporter.step(step=state.step, loss=value, lr=lr)
    return value, lr


def validate(run: Run, state: TrainState) -> None:
    """Validate (nothing without a validation set); write the best weights when they are."""
    if run.plan.val is None:
        return
    r = run.recipe
    tv = run.clock()
    vb = r.data.batch_size if r.data.val_crop else 1
    mid, seq, _ = evaluate(run.judged, run.plan.val, dist=run.dist, batch_size=vb,
                           amp_dtype=run.val_dtype, fallback_contrast=r.loss.contrast)
    state.val_time = run.clock() - tv
    state.last_val.update(psnr_mid=mid, psnr_seq=seq, step=state.step)
    run.reporter.validated(step=state.step, psnr_mid=mid, psnr_seq=seq)
    if state.best["psnr_mid"] is None or mid > state.best["psnr_mid"]:
        state.best.update(psnr_mid=mid, psnr_seq=seq, step=state.step)
        if run.dist.is_main:
            state.best_path = save_run_weights(run.run_dir / "best.safetensors", run, state)


def log_row(run: Run, state: TrainState, loss: float | None, lr: float, val: bool) -> None:
    """Add the log row of this step, or fill in the one it already has."""
    entry: dict[str, Any] = {"step": state.step, "epoch": state.step / run.bpe, "loss": loss,
                             "lr": lr,
                             "val_psnr_mid": state.last_val["psnr_mid"] if val else None,
                             "val_psnr_seq": state.last_val["psnr_seq"] if val else None,
                             "seconds": run.elapsed(state)}
    history = state.history
    if history and history[-1]["step"] == state.step:
        history[-1].update({k: v for k, v in entry.items() if v is not None})
    else:
        history.append(entry)


def checkpoint(run: Run, state: TrainState) -> None:
    """Write the checkpoint and the log and curve (rank 0), and wait for every process."""
    r, s = run.recipe, state
    tc = run.clock()
    if run.dist.is_main:
        save_checkpoint(run.run_dir / CHECKPOINT, model=run.bare, optimizer=run.optimizer,
                        scaler=run.scaler, ema=run.ema,
                        state={"step": s.step, "total_steps": run.total,
                               "epoch": s.step // run.bpe,
                               "skip": (s.step % run.bpe) * r.data.batch_size,
                               "batches_per_epoch": run.bpe, "seconds": run.elapsed(s),
                               "history": s.history, "best": s.best, "last_val": s.last_val,
                               "loss_acc": s.loss_acc, "recipe": r.to_dict(),
                               "recipe_base_dir": r.base_dir, "data": run.data_paths,
                               "world": run.dist.world})
        write_outputs(run.run_dir, s.history, r.name)
    ddp.barrier(run.dist)
    state.last_ckpt = run.clock()
    state.ckpt_time = state.last_ckpt - tc


# --------------------------------------------------------------------------------------------
# Outputs


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


def write_outputs(run_dir: Path, history: Sequence[dict], title: str) -> None:
    """``log.csv`` and ``curve.png`` from the log rows."""
    from .plots import write_curve

    _write_log(run_dir / "log.csv", history)
    write_curve(run_dir / "curve.png", history, title=title)


def recipe_record(recipe: Recipe) -> dict[str, Any]:
    """The recipe as metadata records it: ``data.val_data`` by its file name, not its path on
    this machine (``plan.val_record`` has its SHA-256)."""
    doc = recipe.to_dict()
    data = doc.get("data") or {}
    if data.get("val_data"):
        data["val_data"] = Path(data["val_data"]).name
    return doc


def save_run_weights(path: Path, run: Run, state: TrainState) -> Path:
    """The weights that are judged (:attr:`Run.judged`) with the run's recipe and figures."""
    from ..models.weights import save_weights

    model, r = run.judged, run.recipe
    last_val, best = state.last_val, state.best
    figures = {"steps": state.step, "total_steps": run.total, "epochs": state.step / run.bpe,
               "train_seconds": round(run.elapsed(state), 1),
               "val_psnr_mid": last_val["psnr_mid"], "val_psnr_seq": last_val["psnr_seq"],
               "val_step": last_val["step"], "best_val_psnr_mid": best["psnr_mid"],
               "best_step": best["step"], "validation": run.plan.val_record}
    meta = {"recipe": recipe_record(r), "figures": figures,
            "training_data": [Path(p).name for p in run.data_paths]}
    with contextlib.suppress(AttributeError):
        if not getattr(model, "variant", None):
            model.variant = r.model.name
    return save_weights(path, model, meta=meta)
