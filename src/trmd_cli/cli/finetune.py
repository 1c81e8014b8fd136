"""`trmd finetune INPUT… -o my-camera.safetensors`: adapt RE-Net to a camera, no ground truth.

INPUT is anything `trmd deblur` takes (a recording, BLURRY EVENTS, a frames folder with its
events, several recordings or a folder of them). The losses need no sharp frame (see
:mod:`trmd_cli.train.finetune`); a held-out share of the windows says whether it helped, and
``<output>.png`` shows one of them: blurry | before | after.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from .boundary import err, guarded, progress_enabled, warn
from .deblur import HotPixels, Pattern, TimeOffset, parse_contrast
from .options import (
    Columns,
    Exposure,
    ExposureLength,
    OneBased,
    Overwrite,
    Sensor,
    Stamp,
    Threads,
    TimeUnit,
    Topics,
    parse_duration_us,
    read_options,
)


def parse_losses(items: list[str]) -> dict[str, float]:
    """``["reblur=1", "warp=0.5"]`` → weights, starting from the defaults (a name given
    replaces its weight; ``=0`` turns a loss off)."""
    from ..errors import InputError
    from ..train.finetune import DEFAULT_LOSSES

    out = dict(DEFAULT_LOSSES)
    for item in items:
        name, sep, value = item.partition("=")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            sep = ""
        if not sep:
            raise InputError(f"--loss {item!r} is not NAME=WEIGHT",
                             hint="e.g. --loss warp=0.25 --loss event_consistency=0")
    return out


def plain_line(done: int, total: int) -> bool:
    """Whether step ``done`` of ``total`` gets a line in a log: the first, every tenth, the
    last."""
    every = max(1, total // 10)
    return done == 1 or done == total or done % every == 0


def picture_path(output: Path) -> Path:
    """Where the before/after picture of a run writing ``output`` goes."""
    return output.with_suffix(".png")


def finetune(
    inputs: Annotated[list[Path], typer.Argument(
        help="What `trmd deblur` takes: RECORDING (several, or a folder of them), BLURRY "
        "EVENTS, IMAGES_DIR EVENTS|EVENTS_DIR.", show_default=False, readable=False)],
    output: Annotated[Path, typer.Option(
        "--output", "-o", help="The fine-tuned weights (.safetensors); a before/after picture "
        "of a held-out frame goes beside it (same name, .png).", readable=False)],
    init_weights: Annotated[Path | None, typer.Option(
        "--init-weights", help="Weights to start from (default: the shipped weights).",
        readable=False)] = None,
    steps: Annotated[int, typer.Option("--steps", min=0, help="Optimiser steps.")] = 300,
    crop: Annotated[int, typer.Option("--crop", min=16, help="Training crops, pixels.")] = 128,
    batch_size: Annotated[int, typer.Option("--batch-size", min=1, help="Crops per step.")] = 4,
    lr: Annotated[float, typer.Option("--lr", help="Learning rate (Adam).")] = 3e-4,
    loss: Annotated[Optional[list[str]], typer.Option(
        "--loss", help="Change a loss weight, NAME=WEIGHT (reblur, warp, deconv, "
        "event_consistency, blur_consistency; default reblur=1, warp=0.25, deconv=1, "
        "event_consistency=0). Repeatable."
    )] = None,
    anchor: Annotated[float, typer.Option(
        "--anchor", help="Pull towards the starting weights (0 = none).")] = 0.01,
    holdout: Annotated[float, typer.Option(
        "--holdout", help="Fraction of the windows held out to judge the result.")] = 0.2,
    max_windows: Annotated[int, typer.Option(
        "--max-windows", min=1, help="At most this many exposures, taken evenly over the "
        "inputs.")] = 240,
    contrast: Annotated[str, typer.Option(
        "--contrast", help="The sensor's contrast threshold c, or 'auto' to estimate it per "
        "frame.")] = "auto",
    seed: Annotated[int, typer.Option("--seed", help="Random seed of the crops.")] = 0,
    parts: Annotated[Optional[str], typer.Option(
        "--parts", help="Train only these parts of the network, comma-separated (e.g. "
        "refine,head,up4,up3; `trmd info` on weights does not list them: an unknown name is "
        "refused with the list). Default: all.")] = None,
    hot_pixels: HotPixels = True,
    remove_pattern: Pattern = True,
    exposure: Exposure = None,
    time_offset: TimeOffset = None,
    threads: Threads = None,
    time_unit: TimeUnit = None,
    sensor: Sensor = None,
    columns: Columns = None,
    one_based: OneBased = False,
    exposure_length: ExposureLength = None,
    stamp: Stamp = None,
    topics: Topics = None,
    overwrite: Overwrite = False,
) -> None:
    """Fine-tune the network on your own recordings, without sharp frames: moved along the
    motion the events show, the middle frame must re-blur into the blurry one and become the
    other frames, as the deconvolution along that motion says. Writes weights that deblur,
    hfr, eval and info take, and prints the losses on held-out exposures before and after."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from ..errors import InputError
    from ..models.weights import save_weights
    from ..train.finetune import FinetuneConfig
    from ..train.finetune import finetune as run
    from ..viz import strip
    from ..write import check_output, write_image

    if output.suffix.lower() != ".safetensors":
        raise InputError("-o must name a .safetensors file", path=output,
                         hint="e.g. -o my-camera.safetensors")
    config = FinetuneConfig(steps=steps, crop=crop, batch_size=batch_size, lr=lr,
                            losses=parse_losses(loss or []), anchor=anchor, holdout=holdout,
                            max_windows=max_windows, contrast=parse_contrast(contrast),
                            hot_pixels=hot_pixels, fixed_pattern=remove_pattern, seed=seed,
                            trainable=tuple(x.strip() for x in (parts or "").split(",")
                                            if x.strip()))
    offset = parse_duration_us(time_offset) if time_offset else 0
    opts = read_options(columns, one_based, time_unit, sensor, exposure_length, stamp, topics)
    guard = [*inputs, init_weights]
    check_output(output, overwrite, inputs=guard)
    picture = picture_path(output)
    check_output(picture, overwrite, inputs=guard)

    started = time.monotonic()
    with Progress(TextColumn("{task.description}"), BarColumn(bar_width=24),
                  MofNCompleteColumn(), TextColumn("{task.fields[stats]}"),
                  TimeElapsedColumn(), TimeRemainingColumn(), console=err,
                  disable=not progress_enabled(), transient=True) as bar:
        tasks: dict[str, int] = {}
        plain = not progress_enabled()

        def progress(phase: str, done: int, total: int, figures: dict[str, float]) -> None:
            if plain:
                # a log file gets a line per tenth of the training: minutes of silence read as
                # a hang. Reading windows stays quiet: a bad input there still gets one line.
                if phase == "train" and plain_line(done, total):
                    err.print(f"fine-tuning step {done}/{total}: loss {figures['loss']:.4g} "
                              f"({time.monotonic() - started:.0f} s)", highlight=False,
                              markup=False, soft_wrap=True)
                return
            if phase not in tasks:
                label = "reading windows" if phase == "windows" else "fine-tuning"
                tasks[phase] = bar.add_task(label, total=total, stats="")
            stats = f"loss {figures['loss']:.4g}" if "loss" in figures else ""
            bar.update(tasks[phase], completed=done, total=total, stats=stats)

        result, notes = run(inputs, weights=init_weights, config=config, read_options=opts,
                            exposure=exposure, offset_us=offset, threads=threads,
                            progress=progress)
    for line in notes:
        warn(line)

    if result.example is not None:
        name, blurry, before, after = result.example
        write_image(picture, strip([blurry, before, after], ["blurry", "before", "after"]))
    elif picture.is_file():
        # (overwrite): an earlier run's picture would stand beside weights it does not show
        picture.unlink()
    save_weights(output, result.model, meta=result.meta)

    typer.echo(f"fine-tuned {config.steps} steps on {result.windows} window(s) "
               f"({result.trusted} with a reliable motion) in "
               f"{time.monotonic() - started:.0f} s")
    if result.held_out:
        parts = [f"{k} {result.before[k]:.4g} → {result.after[k]:.4g}"
                 for k in result.before if k in result.after]
        typer.echo(f"held-out losses ({result.held_out} window(s)): " + ", ".join(parts))
        typer.echo(f"picture: {picture} (blurry | before | after, {result.example[0]})")
    else:
        warn("no window was held out (one window, or --holdout 0): nothing says whether the "
             "fine-tuning helped")
    typer.echo(f"weights: {output}  (use: trmd deblur … --weights {output})")


def register(app: typer.Typer) -> None:
    app.command(name="finetune")(guarded(finetune))
