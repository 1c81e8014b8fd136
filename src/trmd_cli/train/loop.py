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

Weights and ``recipe.json`` name the validation set by its file name and SHA-256, not by its
path on the training machine (:func:`~.data.data_record`). The loop itself is
:func:`~.steps.step`, :func:`~.steps.validate` and :func:`~.steps.checkpoint` over a
:class:`~.steps.TrainState`; this module decides when each happens.

Reproducibility: every random choice is seeded from the recipe (model init from ``seed``, sample
order and crops from (seed, epoch, index)), and checkpoints hold the RNG states, optimiser and
log, so an interrupted run resumed with ``resume=True`` ends with the weights an uninterrupted
run would have produced (to floating-point tolerance).
"""

from __future__ import annotations

import os
import random
import re
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import torch

from ..errors import InputError, OutputExistsError, WeightsError
from ..precision import precision_name, resolve_precision
from . import ddp
from .checkpoint import load_checkpoint, read_checkpoint_state
from .data import DataPlan, EpochSampler, build_data, set_epoch
from .ema import WeightAverage
from .losses import SUPERVISED
from .recipe import (
    RESUME_LENGTH_KEYS,
    RESUME_SAFE_KEYS,
    Recipe,
    apply_overrides,
    load_recipe,
    recipe_diff,
    recipe_from_dict,
)
from .steps import (
    CHECKPOINT,
    LOG_COLUMNS,
    Run,
    TrainState,
    checkpoint,
    evaluate,
    forward,
    log_row,
    lr_at,
    recipe_record,
    save_run_weights,
    step,
    validate,
    write_outputs,
)

if TYPE_CHECKING:
    from ..models.grow import Grown

__all__ = ["train", "TrainResult", "Reporter", "lr_at", "evaluate", "forward", "LOG_COLUMNS",
           "CHECKPOINT", "RUN_FILES", "build_model"]

#: every file a run writes into its folder
RUN_FILES = (CHECKPOINT, "log.csv", "curve.png", "best.safetensors", "final.safetensors",
             "recipe.json")
#: the temporary file safetensors' save_file makes beside its target (Rust tempfile)
_SAFETENSORS_TEMP = re.compile(r"\.tmp[A-Za-z0-9]{6}")


class Reporter(Protocol):
    """What the loop tells its caller. All methods are optional to act upon."""

    def phase(self, message: str) -> None: ...
    def start(self, *, total: int, done: int, info: dict[str, Any]) -> None: ...
    def step(self, *, step: int, loss: float, lr: float) -> None: ...
    def validated(self, *, step: int, psnr_mid: float, psnr_seq: float) -> None: ...
    def note(self, message: str) -> None: ...
    def close(self) -> None: ...


class _Silent:
    def phase(self, message: str) -> None: ...
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
    stopped: str  # "done", "time_budget" or "step_limit"
    val_psnr_mid: float | None
    val_psnr_seq: float | None
    best_val_psnr_mid: float | None
    best_step: int | None
    final_weights: Path | None
    best_weights: Path | None
    notes: list[str] = field(default_factory=list)


def build_model(recipe: Recipe) -> torch.nn.Module:
    """``create_model(model.name, n=…, channels=…, **model.args)``, with recipe-named errors."""
    from ..models import create_model

    m = recipe.model
    try:
        return create_model(m.name, n=m.n, channels=m.channels, **m.args)
    except TypeError as e:
        raise InputError(f"model.args do not fit model {m.name!r}: {e}",
                         hint="check the keys of [model.args]") from None


def _has_true_contrast(dataset) -> bool:
    """Whether samples carry their sensor's threshold (judged by the first one)."""
    c = dataset[0].get("contrast") if len(dataset) else None
    return c is not None and bool(torch.isfinite(torch.as_tensor(c)).all())


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
                         hint="resume with the run's own recipe (omit `recipe`), or start a new "
                         "run (`init_weights` to fine-tune from its weights)")
    if any(k in RESUME_LENGTH_KEYS for k in diff):
        notes.append("the run's length changed: the learning-rate schedule differs from the "
                     "original run's from here on")
    stored_data = list(state.get("data") or [])
    new_data = [str(Path(p).expanduser().resolve()) for p in (data or [])]
    if new_data and new_data != stored_data:
        raise InputError("`data` differs from the data the run started with", path=ckpt,
                         hint="omit `data` when resuming (the run's own data is used)")
    return recipe, stored_data, state, notes


def train(data: Sequence[str | Path] | None = None, *, recipe: Recipe | None = None,
          run_dir: str | Path, resume: bool = False, init_weights: str | Path | None = None,
          overrides: list[str] | None = None, overwrite: bool = False, device: str = "auto",
          reporter: Reporter | None = None,
          stop_after_steps: int | None = None,
          clock: Callable[[], float] = time.monotonic) -> TrainResult:
    """Train a RE-Net as ``recipe`` says on ``data``, writing into ``run_dir``.

    Args:
        data: ``data`` paths (image folders, trmd HDF5 sets, GOPRO-layout h5); may be None
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
        stop_after_steps: stop (checkpointed, resumable) after this many steps of this call.
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
                                hint="pass `resume=True` to continue it, `overwrite=True` to "
                                "start over, or choose another `run_dir`")
    if resume and init_weights is not None:
        raise InputError("`init_weights` cannot be combined with `resume=True`",
                         hint="a resumed run continues from its own checkpoint")
    recipe, data_paths, resumed, notes = _resolve_run(data, recipe, run_dir, resume,
                                                      overrides)
    if not data_paths:
        raise InputError("no training data given", hint="pass `data` (image folders or .h5 sets)")

    # a fresh run stopped before its first checkpoint leaves nothing: a folder of a recipe and
    # a log that no checkpoint continues would be refused by a rerun and by a resume alike
    existed = run_dir.exists()
    fresh = not resume and not (existed and any(run_dir.iterdir()))
    dist = ddp.setup(device)
    try:
        return _train(recipe, data_paths, run_dir, resumed, init_weights, dist, reporter,
                      stop_after_steps, clock, t_start, notes)
    except BaseException:
        if fresh and dist.rank == 0 and not (run_dir / CHECKPOINT).exists():
            for left in list(run_dir.iterdir()) if existed else [run_dir]:
                if left.is_dir():
                    shutil.rmtree(left, ignore_errors=True)
                else:
                    left.unlink(missing_ok=True)
        raise
    finally:
        ddp.teardown(dist)


def _train(recipe: Recipe, data_paths: list[str], run_dir: Path, resumed: dict | None,
           init_weights: str | Path | None, dist: ddp.Dist, reporter: Reporter,
           stop_after_steps: int | None, clock: Callable[[], float], t_start: float,
           notes: list[str]) -> TrainResult:
    run, state = _setup(recipe, data_paths, run_dir, resumed, init_weights, dist, reporter,
                        clock, t_start, notes)
    r, tr = run.recipe, run.recipe.train
    plan, batch = run.plan, r.data.batch_size
    sampler = EpochSampler(len(plan.train), seed=r.seed, rank=dist.rank, world=dist.world)
    budget = tr.time_budget_minutes * 60.0
    state.last_ckpt = clock()
    stopped = "done"
    start_step = state.step
    final_path = None

    reporter.start(total=run.total, done=state.step, info={
        "run_dir": str(run_dir), "recipe": r.name, "model": r.model.name,
        "train": plan.sources, "validation": plan.val_source, "batches_per_epoch": run.bpe,
        "world": dist.world, "device": str(dist.device), "threads": torch.get_num_threads(),
        "precision": precision_name(run.amp_dtype),
        "resumed_at": state.step if resumed is not None else None})
    for note in notes:
        reporter.note(note)

    if budget and state.seconds_before >= budget and state.step < run.total:
        stopped = "time_budget"  # resumed with the budget already used up: no extra step
    try:
        while state.step < run.total and stopped == "done":
            epoch = state.step // run.bpe
            set_epoch(plan.train, epoch)
            sampler.set_position(epoch, (state.step % run.bpe) * batch)
            loader = torch.utils.data.DataLoader(
                plan.train, batch_size=batch, sampler=sampler, drop_last=True,
                num_workers=r.data.num_workers, pin_memory=dist.device.type == "cuda",
                # a private generator: creating the iterator must not draw from the global RNG
                generator=torch.Generator().manual_seed(r.seed * 1000003 + epoch))
            for raw in loader:
                _, lr = step(run, state, raw)
                limit_reached = (stop_after_steps is not None
                                and state.step - start_step >= stop_after_steps)
                stopped = _after_step(run, state, lr, budget, limit_reached)
                if stopped != "done" or state.step >= run.total:
                    break
    finally:
        reporter.close()

    if stopped in ("done", "time_budget") and dist.is_main:
        final_path = save_run_weights(run_dir / "final.safetensors", run, state)
        if state.best_path is None and (run_dir / "best.safetensors").exists():
            state.best_path = run_dir / "best.safetensors"
    ddp.barrier(dist)
    return TrainResult(run_dir=run_dir, steps=state.step, total_steps=run.total,
                       epochs=state.step / run.bpe, seconds=run.elapsed(state), stopped=stopped,
                       val_psnr_mid=state.last_val["psnr_mid"],
                       val_psnr_seq=state.last_val["psnr_seq"],
                       best_val_psnr_mid=state.best["psnr_mid"], best_step=state.best["step"],
                       final_weights=final_path, best_weights=state.best_path, notes=notes)


def _after_step(run: Run, state: TrainState, lr: float, budget: float,
                limit_reached: bool) -> str:
    """Log, validate, checkpoint as the recipe says after a step; returns why the run stops
    (``"done"``: it goes on, or it has done every step)."""
    tr, dist, s = run.recipe.train, run.dist, state.step
    logged = s % tr.log_every == 0 or s == run.total
    if logged:
        loss_sum, count = ddp.all_reduce_sum(dist, [state.loss_acc[0],
                                                     float(state.loss_acc[1])])
        log_row(run, state, loss_sum / max(count, 1), lr, False)
        state.loss_acc[:] = [0.0, 0]
    if s % tr.val_every == 0 or s == run.total:
        validate(run, state)
        log_row(run, state, None, lr, True)
    # stop while one more step, a validation and two saves still fit the budget; every
    # process must agree, so the clocks' verdicts are summed over processes
    out_of_time = bool(budget) and (run.elapsed(state) + state.step_time + state.val_time
                                    + 2 * state.ckpt_time + 1.0 >= budget)
    due = bool(tr.checkpoint_minutes) and (
        run.clock() - state.last_ckpt >= tr.checkpoint_minutes * 60)
    out_of_time, timed = (v > 0 for v in ddp.all_reduce_sum(
        dist, [float(out_of_time), float(due)]))
    stopped = "done"
    if out_of_time and s < run.total:
        stopped = "time_budget"
    elif limit_reached and s < run.total:
        stopped = "step_limit"
    if stopped == "time_budget" and state.last_val["step"] != s:
        validate(run, state)
        log_row(run, state, None, lr, True)
    if s % tr.checkpoint_every == 0 or timed or s == run.total or stopped != "done":
        checkpoint(run, state)
    elif logged and dist.is_main:
        write_outputs(run.run_dir, state.history, run.recipe.name)
    return stopped


def _setup(recipe: Recipe, data_paths: list[str], run_dir: Path, resumed: dict | None,
           init_weights: str | Path | None, dist: ddp.Dist, reporter: Reporter,
           clock: Callable[[], float], t_start: float, notes: list[str]
           ) -> tuple[Run, TrainState]:
    """Data, network, optimiser and state of a new or resumed run; the run folder prepared.
    The order of everything that draws random numbers is part of what makes runs
    reproducible: seeds, the data plan, the network's initialisation, then the checkpoint."""
    r, tr = recipe, recipe.train
    torch.set_num_threads(_threads(recipe, dist))
    _seed_everything(r.seed)
    supervised = any(w > 0 for k, w in r.loss.weights.items() if k in SUPERVISED)
    # reading or simulating the data can take minutes: say so before, not after
    reporter.phase("preparing the training and validation data")
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

    reporter.phase(f"building {r.model.name}" + (" and loading the checkpoint"
                                                   if resumed is not None else ""))
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

    state = TrainState()
    if resumed is not None:
        doc = load_checkpoint(run_dir / CHECKPOINT, model=model, optimizer=optimizer,
                              scaler=scaler, ema=ema)
        state = TrainState.from_checkpoint(doc)
        if int(doc.get("world", 1)) != dist.world:
            notes.append(f"resumed with {dist.world} process(es), the run started with "
                         f"{doc.get('world')}: the batches differ from an uninterrupted run")
    elif init_weights is not None:
        notes += _grow_notes(_load_init(model, init_weights, r))
    if ema is None and r.optim.ema > 0:
        ema = WeightAverage(model, r.optim.ema)

    bare = model
    if bare.needs.contrast and not _has_true_contrast(plan.train):
        notes.append(f"the training data stores no true contrast threshold: "
                     f"{r.model.name} is given loss.contrast = {r.loss.contrast} "
                     "(set it to your camera's, or train a network without it)")
    if dist.enabled:
        model = torch.nn.parallel.DistributedDataParallel(
            bare, device_ids=[dist.device.index] if dist.device.type == "cuda" else None)
    if dist.is_main:
        _prepare_run_dir(run_dir, fresh=resumed is None)
        from ..write import write_json

        write_json(run_dir / "recipe.json", {"recipe": recipe_record(r), "data": data_paths,
                                             "validation": plan.val_record,
                                             "world": dist.world})
    run = Run(recipe=r, plan=plan, data_paths=data_paths, run_dir=run_dir, dist=dist,
              model=model, bare=bare, optimizer=optimizer, scaler=scaler, ema=ema,
              amp_dtype=amp_dtype, val_dtype=val_dtype, total=total, bpe=bpe,
              reporter=reporter, clock=clock, t0=t_start)
    return run, state


def _prepare_run_dir(run_dir: Path, fresh: bool) -> None:
    run_dir.mkdir(parents=True, exist_ok=True)
    if fresh:  # no stale outputs of an earlier run stay behind
        for name in RUN_FILES:
            (run_dir / name).unlink(missing_ok=True)
    for name in RUN_FILES:  # temporaries of a process killed (-9) while writing
        stem = Path(name).stem
        for tmp in run_dir.glob(f".{stem}.*.tmp*"):
            tmp.unlink(missing_ok=True)
    # what safetensors' own save_file left when killed (-9) inside it (trmd before checkpoints
    # were written as bytes by trmd's atomic writer): ".tmp" and six letters or digits
    for tmp in run_dir.glob(".tmp*"):
        if _SAFETENSORS_TEMP.fullmatch(tmp.name) and tmp.is_file():
            tmp.unlink(missing_ok=True)


def _grow_notes(grown: Grown) -> list[str]:
    """What to tell about a network grown from ``init_weights``."""
    notes = []
    # a wider U-Net grows every layer, the refinement's included: that one note says it all
    added = [] if grown.widened else sorted({k.split(".")[0] for k in grown.identity})
    if added:
        notes.append(f"`init_weights` had no {', '.join(added)} layers: they start as an "
                     "identity, so the run starts from exactly what those weights computed")
    if grown.timing:
        notes.append("`init_weights` had no timing inputs: their weights start at zero, "
                     "so the run starts from exactly what those weights computed")
    if grown.widened:
        notes.append("`init_weights` has a narrower U-Net: the new channels start random, "
                     "their weights into the old ones at zero, so the run starts from "
                     "exactly what those weights computed")
    return notes


def _load_init(model: torch.nn.Module, path: str | Path, recipe: Recipe) -> Grown:
    """Start from a weights file, or from the weights in another run's checkpoint; what was
    grown to fit (:func:`~trmd_cli.models.grow.load_grown`)."""
    from ..models.weights import load_weights
    from .checkpoint import is_checkpoint, load_checkpoint_weights, load_init_state

    if is_checkpoint(path):
        return load_checkpoint_weights(path, model)["grown"]

    src, meta = load_weights(path, expect_n=recipe.model.n,
                             expect_channels=recipe.model.channels)
    try:
        return load_init_state(model, src.state_dict())
    except RuntimeError as e:
        raise WeightsError(f"weights do not fit model {recipe.model.name!r} "
                           f"({str(e).splitlines()[0]})", path=path,
                           hint=f"they are for {meta.get('architecture')}: set model.name and "
                           "model.args to match") from None
