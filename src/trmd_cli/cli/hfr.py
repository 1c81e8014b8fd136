"""`trmd hfr`: a continuous high-frame-rate video from blurry frames and their events.

    trmd hfr BLURRY1.png BLURRY2.png … EVENTS -o slowmo.mp4
    trmd hfr RECORDING.aedat4|.h5 -o slowmo.gif
    trmd hfr IMAGES_DIR EVENTS|EVENTS_DIR -o frames/

Each exposure gives ``--per-exposure K`` frames (default 2N+1, ends included); the gaps between
exposures are filled at the same time step from the events (forward from one exposure, backward
from the next, cross-faded), so the video is continuous. ``--fps`` is only the playback rate.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer

from .boundary import err, guarded, progress_enabled, warn
from .deblur import (
    BitDepth,
    Contrast,
    HotPixels,
    Method,
    NOpt,
    TimeOffset,
    Weights,
    method_config,
)
from .options import (
    Columns,
    Device,
    Exposure,
    OneBased,
    Overwrite,
    Precision,
    Sensor,
    Threads,
    TimeUnit,
    parse_duration_us,
    read_options,
)


def hfr(
    inputs: Annotated[list[Path], typer.Argument(
        help="BLURRY… EVENTS, or RECORDING, or IMAGES_DIR EVENTS|EVENTS_DIR.",
        show_default=False)],
    output: Annotated[Path, typer.Option(
        "--output", "-o", help="slowmo.mp4, slowmo.gif, or a folder for PNG frames.")],
    method: Method = None,
    n: NOpt = None,
    per_exposure: Annotated[int | None, typer.Option(
        "--per-exposure", min=1, max=1000,
        help="Output frames per exposure (default 2N+1). TRMD: instants between its 2N+1 "
        "frames are propagated from the nearest one by event integration.")] = None,
    fps: Annotated[float, typer.Option("--fps", help="Playback rate of the video.")] = 30.0,
    fill_gaps: Annotated[bool, typer.Option(
        "--fill-gaps/--no-fill-gaps", help="Fill the time between exposures from the events "
        "(default on).")] = True,
    max_gap_frames: Annotated[int | None, typer.Option(
        "--max-gap-frames", min=0, help="Most frames per gap (default 4 × per exposure).")] = None,
    exposure: Exposure = None,
    contrast: Contrast = "auto",
    time_offset: TimeOffset = None,
    bit_depth: BitDepth = 8,
    hot_pixels: HotPixels = True,
    weights: Weights = None,
    device: Device = "auto",
    threads: Threads = None,
    precision: Precision = "auto",
    time_unit: TimeUnit = None,
    sensor: Sensor = None,
    columns: Columns = None,
    one_based: OneBased = False,
    overwrite: Overwrite = False,
) -> None:
    """High-frame-rate video: every exposure's latent frames plus the gaps, in time order."""
    from rich.progress import Progress

    from .. import __version__
    from ..errors import InputError
    from ..pipeline import (
        clipped_fraction,
        deblur_frames,
        hfr_stream,
        make_method,
        open_inputs,
    )
    from ..video import VIDEO_SUFFIXES, VideoWriter
    from ..write import atomic_dir, check_output, write_image, write_json, write_text

    config = method_config(method, weights, n, contrast, hot_pixels, device, threads,
                           bit_depth, precision)
    if not (math.isfinite(fps) and fps > 0):
        raise InputError(f"--fps must be a positive number, got {fps}", hint="e.g. --fps 30")
    offset = parse_duration_us(time_offset) if time_offset else 0
    as_video = output.suffix.lower() in VIDEO_SUFFIXES
    if not as_video and output.suffix and not output.is_dir():
        raise InputError(f"unknown output type {output.suffix!r}", path=output,
                         hint="use .mp4, .gif, or a folder")
    check_output(output, overwrite)

    with open_inputs(inputs, read_options(columns, one_based, time_unit, sensor),
                     exposure=exposure, offset_us=offset) as ins:
        for w in ins.warnings:
            warn(w)
        starts = [e.start_us for e in ins.source.exposures()]
        if any(b < a for a, b in zip(starts, starts[1:])):  # noqa: B905 - offset pairs
            raise InputError("the frames are not in time order", path=inputs[0],
                             hint="name the frames so that their numbers follow time")
        est = make_method(config)
        if hasattr(est, "always_contrast"):  # TRMD: the gaps are filled with EDI's model
            est.always_contrast = fill_gaps
        notes: list[str] = []
        contrasts: list[float] = []
        clipped: list[float] = []
        count = {"exposure": 0, "gap": 0}
        lines = ["# file time_us kind source"]

        def results():
            for res in deblur_frames(ins.source, est, per_exposure=per_exposure):
                for w in res.warnings:
                    warn(w)
                if res.estimate.contrast is not None:
                    contrasts.append(res.estimate.contrast)
                clipped.append(clipped_fraction(res.frames))
                bar.advance(task)
                yield res

        with Progress(console=err, disable=not progress_enabled(), transient=True) as bar:
            task = bar.add_task("hfr", total=len(ins.source))
            stream = hfr_stream(results(), ins.source.recording, fill_gaps=fill_gaps,
                                max_gap_frames=max_gap_frames,
                                contrast=config.contrast, notes=notes)
            if as_video:
                with VideoWriter(output, fps) as vw:
                    for fr in stream:
                        vw.append(fr.image)
                        count[fr.kind] += 1
            else:
                with atomic_dir(output) as tmp:
                    for i, fr in enumerate(stream):
                        name = f"{i:06d}.png"
                        write_image(tmp / name, fr.image, bit_depth)
                        lines.append(f"{name} {fr.t_us:.3f} {fr.kind} {fr.source}")
                        count[fr.kind] += 1
                    write_text(tmp / "timestamps.txt", "\n".join(lines) + "\n")
                    write_json(tmp / "meta.json", {
                        "tool": f"trmd {__version__}", "method": est.name, "n": est.n,
                        "weights_hash": est.weights_hash, "inputs": ins.paths,
                        "precision": est.precision,
                        "per_exposure": per_exposure or 2 * est.n + 1, "fps": fps,
                        "fill_gaps": fill_gaps, "time_offset_us": offset,
                        "contrast": contrasts, "frames": count})

    for note in notes:
        warn(note)
    if contrasts:
        import numpy as np

        kind = "given" if config.contrast is not None else "estimated"
        typer.echo(f"contrast threshold c ({kind}): median {np.median(contrasts):.3f}, range "
                   f"{min(contrasts):.3f}–{max(contrasts):.3f}")
    if clipped and max(clipped) > 0:
        warn(f"{100 * sum(clipped) / len(clipped):.2f} % of output values were above 1 and "
             "were clipped to white")
    total = count["exposure"] + count["gap"]
    typer.echo(f"wrote {output}: {total} frames ({count['exposure']} from exposures, "
               f"{count['gap']} filling gaps) at {fps:g} fps, {est.name} N={est.n}")


def register(app: typer.Typer) -> None:
    app.command(name="hfr")(guarded(hfr))
