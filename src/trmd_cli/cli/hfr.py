"""`trmd hfr`: a continuous high-frame-rate video from blurry frames and their events.

    trmd hfr BLURRY1.png BLURRY2.png … EVENTS -o slowmo.mp4
    trmd hfr RECORDING.aedat4|.h5 -o slowmo.gif
    trmd hfr IMAGES_DIR EVENTS|EVENTS_DIR -o frames/
    trmd hfr IMAGES_DIR BINS_FILE -o frames/

Each exposure gives ``--per-exposure K`` frames (default 2N+1, ends included); the gaps between
exposures are filled at the same time step from the events (forward from one exposure, backward
from the next, cross-faded), so the video is continuous. ``--fps`` is only the playback rate.
Binned events have no event times: the stream is the exposures' 2N+1 frames in order, without
gap filling, and timestamps.txt gives each frame's fraction of its exposure.
"""

from __future__ import annotations

import math
from dataclasses import replace
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
    binned_meta,
    method_config,
)
from .options import (
    Columns,
    Device,
    Exposure,
    ExposureLength,
    OneBased,
    Overwrite,
    Precision,
    Sensor,
    Stamp,
    Threads,
    TimeUnit,
    Topics,
    parse_duration_us,
    read_options,
)


def hfr(
    inputs: Annotated[list[Path], typer.Argument(
        help="BLURRY… EVENTS, or RECORDING, or IMAGES_DIR EVENTS|EVENTS_DIR|BINS_FILE.",
        show_default=False, readable=False)],
    output: Annotated[Path, typer.Option(
        "--output", "-o", help="slowmo.mp4, slowmo.gif, or a folder for PNG frames.",
        readable=False)],
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
    exposure_length: ExposureLength = None,
    stamp: Stamp = None,
    topics: Topics = None,
    overwrite: Overwrite = False,
) -> None:
    """High-frame-rate video: every exposure's latent frames plus the gaps, in time order."""
    from rich.progress import Progress

    from .. import __version__
    from ..deblur import ContrastNotes, binned_note, deblur_frames
    from ..errors import InputError
    from ..hfr import check_time_order, hfr_stream
    from ..methods import make_method
    from ..overlap import ahead
    from ..read.inputs import open_inputs
    from ..video import VIDEO_SUFFIXES, VideoWriter
    from ..write import (
        atomic_dir,
        check_output,
        clipped_fraction,
        clipped_message,
        fmt_fraction,
        write_image,
        write_json,
        write_text,
    )

    # the gaps are filled by event integration, which needs c even where the method does not
    config = method_config(method, weights, n, contrast, hot_pixels, device, threads,
                           bit_depth, precision, settle_contrast=fill_gaps)
    if not (math.isfinite(fps) and fps > 0):
        raise InputError(f"--fps must be a positive number, got {fps}", hint="e.g. --fps 30")
    offset = parse_duration_us(time_offset) if time_offset else 0
    as_video = output.suffix.lower() in VIDEO_SUFFIXES
    if not as_video and output.suffix and not output.is_dir():
        raise InputError(f"unknown output type {output.suffix!r}", path=output,
                         hint="use .mp4, .gif, or a folder")
    check_output(output, overwrite, inputs=[*inputs, weights])

    with open_inputs(inputs, read_options(columns, one_based, time_unit, sensor,
                                          exposure_length, stamp, topics),
                     exposure=exposure, offset_us=offset) as ins:
        for w in ins.warnings:
            warn(w)
        if ins.binned:  # in sorted order by definition; no gaps to fill, so no c for them
            config = replace(config, settle_contrast=False)
        else:
            check_time_order(ins.source.exposures(), inputs[0])
        est = make_method(config)
        notes: list[str] = [binned_note(ins.source, est, stream=True)] if ins.binned else []
        contrast_notes = ContrastNotes()
        contrasts: list[float] = []
        clipped: list[float] = []
        count = {"exposure": 0, "gap": 0}
        lines = ["# file fraction kind source (fraction of the source's exposure: binned "
                 "events, no event clock)" if ins.binned else "# file time_us kind source"]

        def results():
            for res in ahead(deblur_frames(ins.source, est, per_exposure=per_exposure)):
                for w in res.warnings:
                    warn(w)
                contrast_notes.add(res)
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
                        when = fmt_fraction(fr.fraction) if fr.t_us is None else \
                            f"{fr.t_us:.3f}"
                        lines.append(f"{name} {when} {fr.kind} {fr.source}")
                        count[fr.kind] += 1
                    write_text(tmp / "timestamps.txt", "\n".join(lines) + "\n")
                    meta = {
                        "tool": f"trmd {__version__}", "method": est.name, "n": est.n,
                        "weights_hash": est.weights_hash, "inputs": ins.paths,
                        "precision": est.precision,
                        "per_exposure": per_exposure or 2 * est.n + 1, "fps": fps,
                        "fill_gaps": fill_gaps, "time_offset_us": offset,
                        "contrast": contrasts, "frames": count}
                    if ins.binned:
                        del meta["time_offset_us"]
                        meta.update(fill_gaps=False, **binned_meta(ins.source))
                    write_json(tmp / "meta.json", meta)

    for note in [*contrast_notes.lines(), *notes]:
        warn(note)
    if contrasts:
        import numpy as np

        kind = "given" if config.contrast is not None else "estimated"
        typer.echo(f"contrast threshold c ({kind}): median {np.median(contrasts):.3f}, range "
                   f"{min(contrasts):.3f}–{max(contrasts):.3f}")
    said = clipped_message(sum(clipped) / len(clipped) if clipped else 0.0)
    if said:
        warn(said)
    total = count["exposure"] + count["gap"]
    typer.echo(f"wrote {output}: {total} frames ({count['exposure']} from exposures, "
               f"{count['gap']} filling gaps) at {fps:g} fps, {est.name} N={est.n}")


def register(app: typer.Typer) -> None:
    app.command(name="hfr")(guarded(hfr))
