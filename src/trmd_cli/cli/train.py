"""`trmd train --data PATH … [--recipe FILE] [--out RUN_DIR] [--resume]`: train RE-Net weights.

Scale-out: ``torchrun --nproc_per_node=K -m trmd_cli train …`` (gloo on CPU, nccl on CUDA);
only rank 0 prints and writes.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from .boundary import err, guarded, progress_enabled, warn
from .options import Device, Overwrite


class _RichReporter:
    """Progress bar with loss, lr and it/s on stderr (rank 0); validation lines always."""

    def __init__(self, show_bar: bool) -> None:
        self.show_bar = show_bar
        self.bar: Any = None
        self.task: Any = None
        self.val = ""
        self._t = time.monotonic()
        self._steps = 0
        self._rate = 0.0

    def phase(self, message: str) -> None:
        # on a terminal only: piped, stderr keeps its promise of one line for bad input
        if self.show_bar:
            err.print(f"[dim]train: {message}…[/]", soft_wrap=True, highlight=False,
                      markup=True)

    def start(self, *, total: int, done: int, info: dict[str, Any]) -> None:
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        resumed = info.get("resumed_at")
        err.print(f"[bold]train[/] {info['recipe']} → {info['run_dir']}  model {info['model']}, "
                  f"{info['world']} process(es) on {info['device']} × {info['threads']} "
                  f"thread(s), {info.get('precision', 'fp32')}"
                  + (f", resumed at step {resumed}" if resumed is not None else ""),
                  soft_wrap=True, highlight=False, markup=True)
        err.print(f"  data: {'; '.join(info['train'])} ({info['batches_per_epoch']} batches "
                  f"per epoch and process); validation: {info['validation']}", soft_wrap=True,
                  highlight=False, markup=False)
        self.bar = Progress(TextColumn("{task.description}"), BarColumn(bar_width=24),
                            MofNCompleteColumn(),
                            TextColumn("{task.fields[stats]}"), TimeElapsedColumn(),
                            TimeRemainingColumn(), console=err, disable=not self.show_bar,
                            transient=False)
        self.bar.start()
        self.task = self.bar.add_task("training", total=total, completed=done, stats="")
        self._t = time.monotonic()

    def step(self, *, step: int, loss: float, lr: float) -> None:
        self._steps += 1
        now = time.monotonic()
        if now - self._t >= 1.0:
            self._rate = self._steps / (now - self._t)
            self._t, self._steps = now, 0
        if self.bar is not None:
            self.bar.update(self.task, completed=step,
                            stats=f"loss {loss:.3g} lr {lr:.1e} {self._rate:.1f} it/s{self.val}")

    def validated(self, *, step: int, psnr_mid: float, psnr_seq: float) -> None:
        self.val = f" val {psnr_mid:.1f}/{psnr_seq:.1f} dB"
        line = (f"step {step}: validation PSNR middle {psnr_mid:.2f} dB, sequence "
                f"{psnr_seq:.2f} dB")
        (self.bar.console if self.bar is not None else err).print(line, highlight=False,
                                                                   markup=False)

    def note(self, message: str) -> None:
        warn(message)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()
            self.bar = None


class _Quiet:
    """Reporter of the processes other than rank 0."""

    def phase(self, message: str) -> None: ...
    def start(self, **_: Any) -> None: ...
    def step(self, **_: Any) -> None: ...
    def validated(self, **_: Any) -> None: ...
    def note(self, message: str) -> None: ...
    def close(self) -> None: ...


def _hms(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def train(
    data: Annotated[list[Path] | None, typer.Option(
        "--data", "-d", help="Training data: image folder (simulated on the fly), HDF5 set from "
        "`trmd simulate`, or GOPRO-layout h5. Repeatable. Optional with --resume.",
        readable=False)] = None,
    recipe: Annotated[Path | None, typer.Option(
        "--recipe", "-r", help="Recipe TOML (default: the one shipped with trmd).",
        readable=False)] = None,
    out: Annotated[Path | None, typer.Option(
        "--out", "-o", help="Run folder for checkpoints, log, curve and weights "
        "(default: ./runs/<recipe name>).", readable=False)] = None,
    resume: Annotated[bool, typer.Option(
        "--resume", help="Continue the run in --out from its checkpoint.")] = False,
    init_weights: Annotated[Path | None, typer.Option(
        "--init-weights", help="Start from these weights (.safetensors), or from the weights "
        "in another run's checkpoint.safetensors, instead of random.", readable=False)
    ] = None,
    set_: Annotated[list[str] | None, typer.Option(
        "--set", help="Change a recipe value, e.g. --set optim.lr=1e-3 --set train.steps=500. "
        "Repeatable.")] = None,
    device: Device = "auto",
    threads: Annotated[Optional[int], typer.Option(
        "--threads", min=1, help="CPU threads per process (default: the recipe's train.threads; "
        "0 there means cores / processes).")] = None,
    stop_after: Annotated[Optional[int], typer.Option(
        "--stop-after", min=1, metavar="STEPS", help="Stop after this many steps in this call, "
        "checkpointed (continue later with --resume); the schedule keeps the recipe's length.")
    ] = None,
    overwrite: Overwrite = False,
) -> None:
    """Train TRMD weights (RE-Net) as a recipe says; resumable, time-budgeted, DDP-ready."""
    from ..errors import InputError, OutputExistsError
    from ..train.loop import train as run_training
    from ..train.recipe import load_recipe

    overrides = list(set_ or [])
    if threads is not None:
        overrides.append(f"train.threads={threads}")
    rec = None
    if recipe is not None or not resume:
        rec = load_recipe(recipe, overrides=overrides)
        overrides = []
    if out is None:
        if resume:
            raise InputError("--resume needs the run folder", hint="pass --out RUN_DIR")
        out = Path("runs") / rec.name  # type: ignore[union-attr]
    if not resume and not data:
        raise InputError("no training data given", hint="pass --data FOLDER_OR_H5 (repeatable)")
    if not resume and out.exists() and not out.is_dir():
        raise InputError("--out is a file, not a folder", path=out, hint="choose a folder")
    if not resume and out.is_dir() and any(out.iterdir()) and not overwrite:
        raise OutputExistsError("the run folder exists and is not empty", path=out,
                                hint="pass --resume to continue, --overwrite to start over, or "
                                "choose another --out")
    is_main = int(os.environ.get("RANK", "0") or 0) == 0
    reporter = _RichReporter(progress_enabled()) if is_main else _Quiet()
    result = run_training(data, recipe=rec, run_dir=out, resume=resume,
                          init_weights=init_weights, overrides=overrides or None,
                          overwrite=overwrite, device=device, reporter=reporter,
                          stop_after_steps=stop_after)
    if not is_main:
        return
    why = {"done": "all steps done", "time_budget": "time budget used up",
           "step_limit": "stopped as asked (--stop-after); continue with --resume"
           }[result.stopped]
    typer.echo(f"trained {result.steps}/{result.total_steps} steps ({result.epochs:.2f} epochs) "
               f"in {_hms(result.seconds)}: {why}")
    if result.val_psnr_mid is not None:
        best = (f"; best middle {result.best_val_psnr_mid:.2f} dB at step {result.best_step}"
                if result.best_val_psnr_mid is not None else "")
        typer.echo(f"validation PSNR: middle {result.val_psnr_mid:.2f} dB, sequence "
                   f"{result.val_psnr_seq:.2f} dB{best}")
    if result.final_weights is not None:
        typer.echo(f"weights: {result.final_weights}"
                   + (f" (best: {result.best_weights})" if result.best_weights else ""))
    typer.echo(f"log: {out / 'log.csv'}, curve: {out / 'curve.png'}")


def register(app: typer.Typer) -> None:
    app.command(name="train")(guarded(train))
