"""`trmd voxelize EVENTS -o voxels.npz`: SCER voxels per exposure window."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from .boundary import err, guarded, progress_enabled, warn
from .options import (
    Columns,
    Exposure,
    ExposureLength,
    N,
    OneBased,
    Overwrite,
    Sensor,
    Stamp,
    TimeUnit,
    Topics,
    parse_duration_us,
    read_options,
)


def voxelize(
    events: Annotated[Path, typer.Argument(help="Event file.", readable=False)],
    output: Annotated[Path, typer.Option("--output", "-o", help="Output .npz.", readable=False)],
    n: N = 3,
    exposure: Exposure = None,
    sensor: Sensor = None,
    time_unit: TimeUnit = None,
    columns: Columns = None,
    one_based: OneBased = False,
    exposure_length: ExposureLength = None,
    stamp: Stamp = None,
    topics: Topics = None,
    time_offset: Annotated[Optional[str], typer.Option(
        "--time-offset", help="Shift the exposure window(s), e.g. -40ms.")] = None,
    preview: Annotated[Optional[Path], typer.Option(
        "--preview", help="Write a red/blue PNG strip of the first window's 2N channels.",
        readable=False)] = None,
    overwrite: Overwrite = False,
) -> None:
    """Write SCER voxels: `voxels` float32 (windows, 2N, H, W), `exposure` int64 µs (windows, 2)."""
    import numpy as np
    from rich.progress import Progress

    from ..read import open_events
    from ..read.paths import check_input_path
    from ..viz import voxel_preview
    from ..voxel import event_bins, scer_from_bins, voxel_instants
    from ..window import resolve_windows
    from ..write import check_image_suffix, check_output, write_image, write_npz

    if output.suffix.lower() != ".npz":
        raise typer.BadParameter("the output must end in .npz", param_hint="--output")
    offset = parse_duration_us(time_offset) if time_offset else 0
    check_input_path(events)
    with open_events(events, read_options(columns, one_based, time_unit, sensor,
                                          exposure_length, stamp, topics)) as rec:
        check_output(output, overwrite, inputs=[events])
        if preview is not None:
            check_image_suffix(preview)  # (never the .npz output's path, then)
            check_output(preview, overwrite, inputs=[events, output])
        for w in rec.warnings:
            warn(w)
        plan = resolve_windows(rec, exposure, time_unit, offset_us=offset)
        for w in plan.warnings:
            warn(w)
        vox = np.zeros((len(plan.windows), 2 * n, rec.height, rec.width), np.float32)
        empty = 0
        with Progress(console=err, disable=not progress_enabled(), transient=True) as bar:
            task = bar.add_task("voxelizing", total=len(plan.windows))
            for i, win in enumerate(plan.windows):
                # SCER voxels add up over the events: a window of the whole recording is taken
                # a piece at a time (memory: one piece, not the span); integer counts, so the
                # sum is exactly the one-piece result
                bins = np.zeros((2 * n, rec.height, rec.width), np.float64)
                count = 0
                for ev in rec.iter_events(win.start_us, win.end_us + 1):
                    count += len(ev)
                    bins += event_bins(ev, win, 2 * n)
                empty += count == 0
                vox[i] = scer_from_bins(bins.astype(np.float32))
                bar.advance(task)
    if empty:
        warn(f"{empty} window(s) hold no events (static scene?): their voxels are zero")
    exp = np.array([[w.start_us, w.end_us] for w in plan.windows], np.int64)
    write_npz(output, voxels=vox, exposure=exp, n=np.int64(n))
    if preview is not None:
        labels = [f"V({k})" for k in voxel_instants(n)]
        write_image(preview, voxel_preview(vox[0], labels))
    typer.echo(f"wrote {output}: {len(plan.windows)} window(s) × {2 * n} channels × "
               f"{rec.height}×{rec.width}")


def register(app: typer.Typer) -> None:
    app.command(name="voxelize")(guarded(voxelize))
