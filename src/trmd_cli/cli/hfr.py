"""`trmd hfr`: a continuous high-frame-rate video from blurry frames and their events.

    trmd hfr BLURRY1.png BLURRY2.png … EVENTS -o slowmo.mp4
    trmd hfr RECORDING.aedat4|.h5 -o slowmo.gif
    trmd hfr IMAGES_DIR EVENTS|EVENTS_DIR -o frames/
    trmd hfr IMAGES_DIR BINS_FILE -o frames/
    trmd hfr RECORDINGS_DIR -o OUT/ --jobs 4 [--format mp4]   # OUT/<recording>/ (or .mp4) each

Each exposure gives ``--per-exposure K`` frames (default 2N+1, ends included); the gaps between
exposures are filled at the same time step from the events (forward from one exposure, backward
from the next, cross-faded), so the video is continuous. ``--fps`` is only the playback rate.
Binned events have no event times: the stream is the exposures' 2N+1 frames in order, without
gap filling, and timestamps.txt gives each frame's fraction of its exposure.

With ``--jobs``, torchrun, ``--resume`` or several recordings the run goes through a stage beside
the output (:mod:`trmd_cli.hfr_batch`): exposures, then the gaps, shared out among the processes;
one process numbers the frames and writes each output at the end, equal file for file to a run
in one process.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from contextlib import closing
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from .boundary import as_flags, guarded, warn
from .deblur import (
    BitDepth,
    Contrast,
    HotPixels,
    Isolated,
    Method,
    NOpt,
    Pattern,
    TimeOffset,
    Weights,
    method_config,
    progress_bar,
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
    parse_jobs,
    read_options,
)

if TYPE_CHECKING:
    from ..hfr import ExposureContrast

Jobs = Annotated[str, typer.Option(
    "--jobs", "-j", help="Worker processes on this machine: the exposures are shared out among "
    "them, then the gaps between exposures (torch threads per worker: the cores shared out, "
    "unless --threads). auto (the default): for the motion and fused methods one per core, "
    "each with at least the work of four 346x260 exposures, at most 8, and 1.5 GB of free "
    "memory each; else one. Across machines, launch the command with torchrun instead: each rank "
    "takes exposures rank, rank + world, …, then the gaps alike; rank 0 writes the output once "
    "every rank is done.")]
Resume = Annotated[bool, typer.Option(
    "--resume", help="Continue an unfinished run of this output (interrupted, or a rank that "
    "failed): the exposures and gaps already complete are kept, the rest made. Runs with "
    "--jobs, torchrun, several recordings or --resume keep them in .OUT.trmd-partial beside -o "
    "until the output is written whole.")]
Format = Annotated[str | None, typer.Option(
    "--format", help="What each recording becomes in the -o folder when there are several: "
    "frames (a folder of PNGs, the default), mp4 or gif. With one input the suffix of -o says "
    "it.", show_default=False)]


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
    drop_isolated: Isolated = True,
    remove_pattern: Pattern = True,
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
    jobs: Jobs = "auto",
    resume: Resume = False,
    fmt: Format = None,
) -> None:
    """High-frame-rate video: every exposure's latent frames plus the gaps, in time order.

    Several recordings (REC1 REC2 …, or a folder of .h5/.aedat4/.aedat/.bag files and recording
    folders) give one output each in the -o folder, named after the recording. Runs that share
    the work out (--jobs, torchrun) or may be resumed keep the finished exposures and gaps in
    .OUT.trmd-partial beside -o meanwhile; with the same --threads the output equals a run in
    one process file for file (on other thread counts the trmd and fused methods' network may
    round a few pixels to the next grey level)."""
    from ..batch import (
        choose_jobs,
        count_work,
        discard_stage,
        ranks_from_env,
        recordings_in,
        staged,
    )
    from ..deblur import ContrastNotes, binned_note, deblur_frames, settle
    from ..errors import InputError
    from ..hfr import (
        ExposureContrast,
        check_time_order,
        contrast_meta,
        hfr_stream,
        timestamp_row,
    )
    from ..hfr_batch import OUTPUT_KINDS, hfr_meta, timestamps_header
    from ..methods import make_method
    from ..overlap import ahead
    from ..read.inputs import open_inputs
    from ..video import VIDEO_SUFFIXES, VideoWriter, check_fps
    from ..write import (
        atomic_dir,
        check_output,
        clipped_fraction,
        write_image,
        write_json,
        write_text,
    )

    # every option is checked before any file is opened or written
    requested_jobs = parse_jobs(jobs)
    kind = None if fmt is None else fmt.lower()
    if kind is not None and kind not in OUTPUT_KINDS:
        raise InputError(f"--format {fmt!r} is not one of {', '.join(OUTPUT_KINDS)}",
                         hint="e.g. --format mp4")
    recordings = recordings_in(inputs)
    # the gaps are filled by event integration, which needs c even where the method does not
    config = method_config(method, weights, n, contrast, hot_pixels, device, threads,
                           bit_depth, precision, settle_contrast=fill_gaps,
                           drop_isolated=drop_isolated, fixed_pattern=remove_pattern)
    if not (math.isfinite(fps) and fps > 0):
        raise InputError(f"--fps must be a positive number, got {fps}", hint="e.g. --fps 30")
    offset = parse_duration_us(time_offset) if time_offset else 0
    opts = read_options(columns, one_based, time_unit, sensor, exposure_length, stamp, topics)
    as_video = output.suffix.lower() in VIDEO_SUFFIXES
    if as_video:
        check_fps(output, fps)
    if recordings is not None:
        if as_video:
            raise InputError("-o names a video, but several recordings give one output each",
                             path=output, hint=f"use -o FOLDER --format "
                             f"{output.suffix.lower()[1:]}: FOLDER/<recording>"
                             f"{output.suffix.lower()} each")
    elif kind is not None and kind != (output.suffix.lower()[1:] if as_video else "frames"):
        raise InputError(f"--format {kind} disagrees with -o {output.name}", path=output,
                         hint="with one input the suffix of -o says what is written: leave "
                         "out --format")
    if not as_video and output.suffix and not output.is_dir():
        raise InputError(f"unknown output type {output.suffix!r}", path=output,
                         hint="use .mp4, .gif, or a folder")
    ranks = ranks_from_env()
    jobs = choose_jobs(requested_jobs, config, lambda: count_work(
        inputs, recordings, opts, exposure, offset), ranks=ranks)
    if staged(jobs, resume, ranks, recordings):
        from ..batch import run_staged
        from ..hfr import CAPPED_NOTE
        from ..hfr_batch import HfrSettings, make_hfr_plan

        kind = kind or (output.suffix.lower()[1:] if as_video else "frames")
        settings = HfrSettings(config, opts, None if exposure is None else tuple(exposure),
                               offset, bit_depth, per_exposure, fill_gaps, max_gap_frames,
                               fps, kind)
        run = run_staged(make_hfr_plan, inputs, recordings, settings, output, ranks=ranks,
                         jobs=jobs, resume=resume, overwrite=overwrite,
                         guard=[*inputs, weights],
                         suffix="" if kind == "frames" else f".{kind}",
                         folder=kind == "frames" or recordings is not None, warn=warn,
                         say=typer.echo, progress=progress_bar)
        if run.main:
            done, meta = run.summary, run.plan.items[0].meta
            if done.capped:
                warn(CAPPED_NOTE)
            _report(output, done.exposure, done.gap, done.contrasts, done.clipped,
                    config.contrast, fps, meta["method"], meta["n"], len(run.plan.items),
                    [it.settled for it in run.plan.items])
        return
    check_output(output, overwrite, inputs=[*inputs, weights], folder=not as_video)

    with open_inputs(inputs, opts, exposure=exposure, offset_us=offset) as ins:
        for w in ins.warnings:
            warn(w)
        discard_stage(output, warn)
        if ins.binned:  # in sorted order by definition; no gaps to fill, so no c for them
            config = replace(config, settle_contrast=False)
        else:
            check_time_order(ins.source.exposures(), inputs[0])
        est, settled = settle(make_method(config), ins.source, config)
        notes: list[str] = [binned_note(ins.source, est, stream=True)] if ins.binned else []
        contrast_notes = ContrastNotes()
        contrasts: list[ExposureContrast] = []
        clipped: list[float] = []
        count = {"exposure": 0, "gap": 0}
        lines = [timestamps_header(ins.binned)]

        def results():
            with closing(ahead(deblur_frames(ins.source, est,
                                             per_exposure=per_exposure))) as made:
                for res in made:
                    for w in res.warnings:
                        warn(w)
                    contrast_notes.add(res)
                    contrasts.append(ExposureContrast.of(res))
                    clipped.append(clipped_fraction(res.frames))
                    tick()
                    yield res

        with progress_bar("hfr", len(ins.source)) as tick:
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
                        lines.append(f"{name} {timestamp_row(fr)}")
                        count[fr.kind] += 1
                    write_text(tmp / "timestamps.txt", "\n".join(lines) + "\n")
                    meta = hfr_meta(ins, est, per_exposure=per_exposure, fps=fps,
                                    fill_gaps=fill_gaps, offset_us=offset, config=config,
                                    settled=settled)
                    write_json(tmp / "meta.json", {**meta, **contrast_meta(contrasts),
                                                   "frames": count})

    for note in [*contrast_notes.lines(), *notes]:
        warn(note)
    _report(output, count["exposure"], count["gap"], contrasts, clipped, config.contrast,
            fps, est.name, est.n, 1, [settled])


def _report(output: Path, exposure: int, gap: int, contrasts: Sequence[ExposureContrast],
            clipped: Sequence[float], given: float | None, fps: float, method: str,
            n: int, recordings: int = 1, settled: Sequence = ()) -> None:
    """``settled``: what was settled for each recording (a ``Settled``) or None."""
    from ..write import clipped_message

    for done in settled:
        for line in [] if done is None else done.lines():
            typer.echo(as_flags(line))
    values = [r.contrast for r in contrasts if r.contrast is not None]
    defaults = sum(r.default for r in contrasts)
    if values and not (settled and all(d is not None and d.contrast is not None
                                       for d in settled)):
        import numpy as np

        kind = "given" if given is not None else "estimated" if defaults == 0 else \
            "the default: too few events to estimate it" if defaults == len(values) else \
            f"estimated; {defaults} of {len(values)} exposures took the default: too few " \
            "events to estimate it"
        typer.echo(f"contrast threshold c ({kind}): median {np.median(values):.3f}, range "
                   f"{min(values):.3f}–{max(values):.3f}")
    said = clipped_message(sum(clipped) / len(clipped) if clipped else 0.0)
    if said:
        warn(said)
    from ..video import played_fps

    typer.echo(f"wrote {output}: {exposure + gap} frames ({exposure} from exposures, "
               f"{gap} filling gaps) at {played_fps(output, fps):.4g} fps, {method} N={n}")
    if recordings > 1:
        typer.echo(f"  from {recordings} recordings, one output each")


def register(app: typer.Typer) -> None:
    app.command(name="hfr")(guarded(hfr))
