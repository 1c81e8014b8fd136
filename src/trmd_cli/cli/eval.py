"""`trmd eval DATASET…`: score deblurring methods, against ground truth or without it."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Annotated

import typer

from .boundary import err, guarded, progress_enabled, warn
from .deblur import Isolated, Pattern
from .options import (
    Columns,
    Device,
    ExposureLength,
    N,
    OneBased,
    Overwrite,
    Precision,
    Sensor,
    Stamp,
    Threads,
    TimeUnit,
    Topics,
    read_options,
)

#: notes printed per dataset (per-frame warnings can be many); --json keeps them all
_MAX_NOTES = 8
#: (figure, header, format) of the table columns with and without ground truth
_GT_COLUMNS = (("psnr_mid", "PSNR mid", "{:.2f}"), ("psnr_seq", "PSNR seq", "{:.2f}"),
               ("ssim_mid", "SSIM mid", "{:.4f}"), ("ssim_seq", "SSIM seq", "{:.4f}"))
_LPIPS_COLUMNS = (("lpips_mid", "LPIPS mid", "{:.4f}"), ("lpips_seq", "LPIPS seq", "{:.4f}"))
_NOGT_COLUMNS = (("sharpness", "sharpness", "{:.5f}"), ("noise", "noise σ", "{:.4f}"),
                 ("explained", "events explained", "{:.3f}"),
                 ("consistency", "consistency err", "{:.4f}"), ("contrast", "c", "{:.3f}"))


def eval_command(
    datasets: Annotated[list[Path], typer.Argument(
        help="Datasets: trmd HDF5 (from `trmd simulate`), GOPRO-style HDF5, a folder with "
             "blurry/ + events (or a bins file) + sharp/, or any recording with frames (no "
             "ground truth).", readable=False)],
    methods: Annotated[str, typer.Option(
        "--methods", help="Comma-separated: blurry, edi, edi-true-c (EDI with a simulated "
        "set's true c), trmd, motion, motion-true-path (motion deconvolution along a simulated "
        "set's true camera path instead of the estimated one: the estimate's cost, as the gap "
        "between the two rows), fused (trmd and motion fused by a small trained network).")
    ] = "blurry,edi,trmd",
    n: N = 3,
    json_out: Annotated[Path | None, typer.Option(
        "--json", help="Also write every figure (per frame and means) to this JSON file.",
        readable=False)] = None,
    limit: Annotated[int | None, typer.Option(
        "--limit", min=1, help="Evaluate only the first K frames of each dataset.")] = None,
    weights: Annotated[Path | None, typer.Option(
        "--weights", help="RE-Net weights (.safetensors) for trmd; default: the shipped "
                          "weights (trmd is skipped when there are none).", readable=False)] = None,
    gt: Annotated[bool | None, typer.Option(
        "--gt/--no-gt", help="Require ground truth, or judge without it (sharpness, noise, the "
                             "events the middle frame explains, event consistency). Default: "
                             "whichever each dataset allows.")] = None,
    strip: Annotated[Path | None, typer.Option(
        "--strip", help="Write a compare strip (blurry | methods | ground truth) per frame "
                        "into this folder.", readable=False)] = None,
    overwrite: Overwrite = False,
    device: Device = "auto",
    threads: Threads = None,
    precision: Precision = "auto",
    drop_isolated: Isolated = True,
    remove_pattern: Pattern = True,
    time_unit: TimeUnit = None,
    columns: Columns = None,
    one_based: OneBased = False,
    sensor: Sensor = None,
    exposure_length: ExposureLength = None,
    stamp: Stamp = None,
    topics: Topics = None,
) -> None:
    """Score deblurring methods: PSNR/SSIM against ground truth (middle frame and all 2N+1),
    or sharpness, noise, the share of the events the middle frame explains and event
    consistency on real recordings without it.

    On sets that `trmd simulate` made from a still image, `--methods motion,motion-true-path`
    puts the motion method beside itself given the true camera path (stored as frames/motion):
    the difference is what the estimated motion costs. A set without a stored path is refused
    for motion-true-path."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

    from ..errors import InputError
    from ..evaluate import evaluate, parse_methods
    from ..read.paths import check_input_path
    from ..write import atomic_dir, check_output, write_json

    for d in datasets:
        check_input_path(d)
    chosen = parse_methods(methods)
    if weights is not None and not {"trmd", "fused"} & set(chosen):
        warn("--weights is ignored: neither trmd nor fused is among --methods")
    if json_out is not None and strip is not None and \
            os.path.abspath(json_out) == os.path.abspath(strip):
        raise InputError("--json and --strip name the same path", path=strip,
                         hint="give the JSON file and the strips' folder different names")
    if json_out is not None:
        check_output(json_out, overwrite, inputs=[*datasets, weights], folder=False)
    if strip is not None:
        check_output(strip, overwrite, inputs=[*datasets, weights], folder=True)
    options = read_options(columns, one_based, time_unit, sensor,
                           exposure_length, stamp, topics)
    progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                        console=err, disable=not progress_enabled(), transient=True)
    tasks: dict[str, int] = {}

    def advance(path: str, done: int, total: int) -> None:
        if path not in tasks:
            tasks[path] = progress.add_task(f"eval {Path(path).name}", total=total)
        progress.update(tasks[path], completed=done, total=total)

    def run(on_frame=None):
        with progress:
            return evaluate(datasets, chosen, n, limit, weights, advance, ground_truth=gt,
                            options=options, on_frame=on_frame, device=device, threads=threads,
                            precision=precision, drop_isolated=drop_isolated,
                            fixed_pattern=remove_pattern)

    if strip is None:
        report = run()
    else:
        with atomic_dir(strip) as tmp:
            report = run(_strip_writer(tmp, datasets, n))
    for note in report.notes:
        warn(note)
    for d in report.datasets:
        notes = [note for note in d.notes if note not in report.notes]
        for note in notes[:_MAX_NOTES]:
            warn(note)
        if len(notes) > _MAX_NOTES:
            warn(f"… and {len(notes) - _MAX_NOTES} more notes on {d.path} (all are in --json)")
    _print_tables(report)
    if json_out is not None:
        write_json(json_out, report.to_dict())
        err.print(f"wrote {json_out}")
    if strip is not None:
        err.print(f"wrote compare strips to {strip}")


def _strip_writer(folder: Path, datasets: list[Path], n: int):
    """An ``on_frame`` callback writing ``<dataset>_<frame>.png`` strips into ``folder``."""
    from ..viz import strip as make_strip
    from ..write import write_image

    stems: dict[str, str] = {}
    for i, p in enumerate(datasets):
        stem = Path(p).stem or f"dataset{i}"
        stems[str(Path(p))] = stem if stem not in stems.values() else f"{stem}-{i}"

    def on_frame(out) -> None:
        f = out.frame
        tiles, labels = [f.blurry], ["blurry"]
        for m, img in out.middle.items():
            if m == "blurry":
                continue
            s = out.scores[m]
            tiles.append(img)
            labels.append(m + (f" {s.psnr_mid:.1f} dB" if s.psnr_mid is not None else ""))
        if f.truth is not None:
            tiles.append(f.truth[n])
            labels.append("ground truth")
        name = f"{stems.get(out.dataset, Path(out.dataset).stem)}_{f.index:06d}.png"
        write_image(folder / name, make_strip(tiles, labels))

    return on_frame


def _fmt(value, pattern: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    return pattern.format(value)


def _print_tables(report) -> None:
    from rich.console import Console
    from rich.table import Table

    from ..evaluate import NO_GT_READING

    console = Console()
    lpips = any(f.lpips_mid is not None for d in report.datasets for m in d.methods
                for f in m.frames)
    for d in report.datasets:
        cols = (_GT_COLUMNS + (_LPIPS_COLUMNS if lpips else ())) if d.ground_truth \
            else _NOGT_COLUMNS
        kind = "ground truth" if d.ground_truth else "no ground truth"
        t = Table(title=f"{d.path} ({d.kind}, {kind}, N={d.n}, {d.size[0]}x{d.size[1]})",
                  title_justify="left",
                  caption=None if d.ground_truth else NO_GT_READING, caption_justify="left")
        t.add_column("method")
        for _, head, _ in cols:
            t.add_column(head, justify="right")
        t.add_column("frames", justify="right")
        t.add_column("s/frame", justify="right")
        for r in d.methods:
            if r.skipped:
                t.add_row(r.method, *(["–"] * len(cols)), "0", "skipped")
                continue
            t.add_row(r.method, *(_fmt(r.mean(k), p) for k, _, p in cols),
                      str(len(r.frames)), _fmt(r.mean("seconds"), "{:.3f}"))
        console.print(t)
    for gt in (True, False):
        sets = [d for d in report.datasets if d.ground_truth == gt]
        if len(sets) < 2:
            continue
        cols = (_GT_COLUMNS + (_LPIPS_COLUMNS if lpips else ())) if gt else _NOGT_COLUMNS
        kind = "with" if gt else "without"
        t = Table(title=f"overall: mean over every frame of {len(sets)} datasets {kind} "
                        "ground truth", title_justify="left")
        t.add_column("method")
        for _, head, _ in cols:
            t.add_column(head, justify="right")
        t.add_column("frames", justify="right")
        t.add_column("s/frame", justify="right")
        for m, figs in report.overall(gt).items():
            t.add_row(m, *(_fmt(figs[k], p) for k, _, p in cols), str(figs["frames"]),
                      _fmt(figs["seconds"], "{:.3f}"))
        console.print(t)


def register(app: typer.Typer) -> None:
    app.command(name="eval")(guarded(eval_command))
