"""`trmd deblur`: blurry frame(s) + events → 2N+1 sharp frames per exposure.

Inputs (see :func:`trmd_cli.read.inputs.open_inputs`)::

    trmd deblur BLURRY.png EVENTS -o OUT/            # OUT/frame_000.png … sharp.png …
    trmd deblur RECORDING.aedat4|.h5 -o OUT/         # OUT/<frame>/… for every stored frame
    trmd deblur IMAGES_DIR EVENTS|EVENTS_DIR -o OUT/ # frames folder, paired by frame number
    trmd deblur IMAGES_DIR BINS_FILE -o OUT/         # binned events (.mat/.npz event_bins, .npy)

A colour blurry frame with mono events is deblurred per channel with the same event ratio
(events carry no colour). Output values above 1 are clipped when written (reported).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer

from ..errors import TrmdError
from .boundary import err, guarded, progress_enabled, warn
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

#: a literal so --help need not import the methods; a test keeps it equal to
#: methods.DEFAULT_METHOD
_DEFAULT_METHOD_HELP = "trmd"

Method = Annotated[str | None, typer.Option(
    "--method", help="edi (model-based, no weights), trmd (learned residuals) or motion "
    "(deconvolution along the events' global motion, guarded by EDI). "
    f"Default: {_DEFAULT_METHOD_HELP}.")]
NOpt = Annotated[int | None, typer.Option(
    "--n", min=1, max=16, help="Latent frames 2N+1 per exposure (default 3 → 7 frames; TRMD: "
    "the weights' N).")]
Contrast = Annotated[str, typer.Option(
    "--contrast", help="Event contrast threshold c (used by EDI and by TRMD), or 'auto' to "
    "estimate it per frame.")]
TimeOffset = Annotated[str | None, typer.Option(
    "--time-offset", help="Shift the exposure window(s) relative to the events, e.g. -40ms "
    "(real DAVIS data often needs tens of ms).")]
Weights = Annotated[Path | None, typer.Option("--weights", help="TRMD weights (.safetensors); "
                                                 "implies --method trmd. Default: the shipped "
                                                 "weights.", readable=False)]
HotPixels = Annotated[bool, typer.Option("--hot-pixels/--keep-hot-pixels",
                                         help="Ignore the events of hot pixels (default on).")]
BitDepth = Annotated[int, typer.Option("--bit-depth", help="PNG bit depth: 8 or 16.")]
Jobs = Annotated[int, typer.Option(
    "--jobs", "-j", help="Worker processes on this machine, each on its share of the frames "
    "(torch threads per worker: the cores shared out, unless --threads). Across machines, "
    "launch the command with torchrun instead: each rank takes frames rank, rank + world, …; "
    "rank 0 writes meta.json and the output once every rank is done.")]
Resume = Annotated[bool, typer.Option(
    "--resume", help="Continue an unfinished run of this output (interrupted, or a rank that "
    "failed): the frames already complete are kept, the rest deblurred. Runs with --jobs, "
    "torchrun, several recordings or --resume keep finished frames in .OUT.trmd-partial "
    "beside -o until the output is swapped in whole.")]


def parse_contrast(text: str) -> float | None:
    """``"auto"`` → None; a positive number → float."""
    from ..errors import InputError

    if text.strip().lower() == "auto":
        return None
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"--contrast {text!r} is not a number or 'auto'",
                         hint="e.g. --contrast 0.25, or --contrast auto") from None
    if not (value > 0 and value < 10):
        raise InputError(f"--contrast {text} must be a positive number (typically 0.1–0.5)",
                         hint="e.g. --contrast 0.25, or --contrast auto")
    return value


def choose_method(method: str | None, weights: Path | None, default: str) -> str:
    """The method to run: ``--weights`` without ``--method`` means TRMD (else a damaged weights
    file would be ignored without a word); with ``--method edi`` it is ignored with a warning."""
    if method is None:
        return "trmd" if weights is not None else default
    if weights is not None and method.lower() != "trmd":
        warn(f"--weights is ignored: --method is {method}")
    return method.lower()


def method_config(method: str | None, weights: Path | None, n: int | None, contrast: str,
                  hot_pixels: bool, device: str, threads: int | None, bit_depth: int,
                  precision: str = "auto", settle_contrast: bool = False):
    """The options deblur and hfr share, checked and turned into a ``MethodConfig``."""
    from ..errors import InputError
    from ..methods import DEFAULT_METHOD, MethodConfig

    config = MethodConfig(method=choose_method(method, weights, DEFAULT_METHOD), n=n,
                          contrast=parse_contrast(contrast), hot_pixels=hot_pixels,
                          weights=weights, device=device, threads=threads,
                          precision=precision, settle_contrast=settle_contrast)
    if bit_depth not in (8, 16):
        raise InputError(f"--bit-depth must be 8 or 16, got {bit_depth}",
                         hint="use --bit-depth 8 or --bit-depth 16")
    return config


def deblur(
    inputs: Annotated[list[Path], typer.Argument(
        help="BLURRY EVENTS, or RECORDING, or IMAGES_DIR EVENTS|EVENTS_DIR|BINS_FILE.",
        show_default=False, readable=False)],
    output: Annotated[Path, typer.Option("--output", "-o", help="Output folder.", readable=False)],
    method: Method = None,
    n: NOpt = None,
    exposure: Exposure = None,
    contrast: Contrast = "auto",
    time_offset: TimeOffset = None,
    compare: Annotated[bool, typer.Option(
        "--compare", help="Also write compare.png (blurry | sharp).")] = False,
    video: Annotated[Path | None, typer.Option(
        "--video", help="Also write the latent frames as a video (.mp4 or .gif).",
        readable=False)] = None,
    fps: Annotated[float, typer.Option("--fps", help="Playback rate of --video.")] = 10.0,
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
    jobs: Jobs = 1,
    resume: Resume = False,
) -> None:
    """Deblur: write 2N+1 sharp frames per blurry frame, plus sharp.png, timestamps.txt and
    meta.json (method, N, c used, weights hash, inputs).

    Several recordings (REC1 REC2 …, or a folder of .h5/.aedat4/.aedat/.bag files and
    recording folders) go to one sub-folder each, named after the recording. The output is
    written whole at the end; runs that share frames out (--jobs, torchrun) or may be resumed
    keep the finished frames in .OUT.trmd-partial beside it meanwhile, so the result is the
    same file for file as a run in one process."""
    from rich.progress import Progress

    from ..batch import frame_folder_name, ranks_from_env, recordings_in, run_meta
    from ..deblur import ContrastNotes, binned_note, deblur_frames
    from ..errors import InputError
    from ..methods import make_method
    from ..overlap import ahead
    from ..read.inputs import open_inputs
    from ..video import VIDEO_SUFFIXES, VideoWriter, check_video_path
    from ..write import atomic_dir, check_output, write_json, write_result_folder

    # every option is checked before any file is opened or written
    if jobs < 1:
        raise InputError(f"--jobs must be at least 1, got {jobs}",
                         hint="e.g. --jobs 4 (one worker process per core)")
    recordings = recordings_in(inputs)
    if len(inputs) > 2 and recordings is None:
        raise InputError(f"deblur takes one or two inputs, got {len(inputs)}",
                         hint="for several images use a frames folder, or `trmd hfr`")
    config = method_config(method, weights, n, contrast, hot_pixels, device, threads,
                           bit_depth, precision)
    if video is not None and not (math.isfinite(fps) and fps > 0):
        raise InputError(f"--fps must be a positive number, got {fps}", hint="e.g. --fps 10")
    offset = parse_duration_us(time_offset) if time_offset else 0
    if output.suffix.lower() in VIDEO_SUFFIXES and not output.is_dir():
        # a folder named like a video would surprise whoever opens it in a player
        raise InputError("-o names a video, but deblur writes a folder of frames", path=output,
                         hint=f"use -o FOLDER --video {output.name}, or `trmd hfr -o "
                         f"{output.name}`")
    ranks = ranks_from_env()
    if jobs > 1 or resume or ranks.enabled or recordings is not None:
        from ..batch import Settings

        if video is not None:
            raise InputError("--video needs every frame in order in one process: not with "
                             "--jobs, --resume, torchrun or several recordings",
                             hint="leave out --video, and make one afterwards with `trmd hfr`")
        if ranks.enabled and jobs > 1:
            raise InputError(f"--jobs {jobs} under torchrun (WORLD_SIZE={ranks.world})",
                             hint="let torchrun start the processes: --nproc_per_node K")
        opts = read_options(columns, one_based, time_unit, sensor, exposure_length, stamp,
                            topics)
        settings = Settings(config, opts, None if exposure is None else tuple(exposure),
                            offset, bit_depth, compare)
        _deblur_batch(inputs, recordings, output, settings, jobs=jobs, resume=resume,
                      overwrite=overwrite, ranks=ranks, guard=[*inputs, weights])
        return
    check_output(output, overwrite, inputs=[*inputs, weights])
    if output.exists() and not output.is_dir():
        raise InputError("the output exists and is not a folder", path=output,
                         hint="choose a folder path for -o")
    if video is not None:
        check_video_path(video)
        # a video inside the output folder would go with the folder it replaces
        check_output(video, overwrite, inputs=[*inputs, weights])
        if output.resolve() in video.resolve().parents:
            raise InputError("--video is inside the -o folder, which deblur replaces whole",
                             path=video, hint="write the video beside the folder")

    with open_inputs(inputs, read_options(columns, one_based, time_unit, sensor,
                                          exposure_length, stamp, topics),
                     exposure=exposure, offset_us=offset) as ins:
        for w in ins.warnings:
            warn(w)
        est = make_method(config)
        meta = run_meta(ins, est, config, offset, bit_depth)
        said = [binned_note(ins.source, est)] if ins.binned else []
        summary: list[dict] = []
        clipped: list[float] = []
        notes = ContrastNotes()
        vw = VideoWriter(video, fps) if video is not None else None
        try:
            with atomic_dir(output) as tmp, Progress(
                    console=err, disable=not progress_enabled() or ins.single,
                    transient=True) as bar:
                task = bar.add_task("deblurring", total=len(ins.source))
                # the next frame is deblurred while this one is written
                for res in ahead(deblur_frames(ins.source, est)):
                    for w in res.warnings:
                        warn(w)
                    notes.add(res)
                    folder = tmp
                    if not ins.single:
                        folder = tmp / frame_folder_name(res.name, res.index)
                        folder.mkdir()
                    info = write_result_folder(folder, res, bit_depth=bit_depth,
                                               compare=compare, meta=meta)
                    summary.append(info)
                    clipped.append(info["clipped_fraction"])
                    if vw is not None:
                        for img in res.frames:
                            vw.append(img)
                    bar.advance(task)
                if not summary:
                    raise InputError("no frame to deblur", hint="check the inputs")
                if not ins.single:
                    write_json(tmp / "meta.json", {**meta, "frames": summary})
                if vw is not None:
                    vw.close()
                    vw = None
        finally:
            if vw is not None:
                vw.abort()

    for line in [*said, *notes.lines()]:
        warn(line)
    _report(summary, clipped, est.name, est.n, output, video, ins.single)


def binned_meta(source) -> dict:
    """What meta.json says about binned events (a ``BinnedSource``): no clock, no µs."""
    from ..batch import binned_meta as meta

    return meta(source)


def _deblur_batch(inputs: list[Path], recordings: list[Path] | None, output: Path, settings,
                  *, jobs: int, resume: bool, overwrite: bool, ranks, guard: list) -> None:
    """A run through a stage (see :mod:`trmd_cli.batch`): one recording or several, in
    ``jobs`` local processes or as one rank of a torchrun launch, resumable."""
    from dataclasses import replace

    from rich.progress import Progress

    from ..batch import (
        Stage,
        agreed,
        finish,
        joined,
        make_plan,
        prepare_stage,
        run_pool,
        run_share,
        worker_threads,
    )
    from ..deblur import ContrastNotes
    from ..errors import InputError
    from ..write import check_output

    groups = [[p] for p in recordings] if recordings is not None else [inputs]
    folders = [p.stem if p.is_file() else p.name for p in recordings] \
        if recordings is not None else [""]
    main = ranks.rank == 0
    stage = Stage(output)
    # per process: the cores of this machine shared out among its processes
    threads = worker_threads(jobs if not ranks.enabled else ranks.local_world,
                             settings.config.threads)
    settings = replace(settings, config=replace(settings.config, threads=threads))

    def check() -> None:
        if not main:
            return
        if resume and not stage.root.is_dir():
            raise InputError("nothing to resume: no unfinished run of this output", path=output,
                             hint="the output is complete already" if output.is_dir()
                             and any(output.iterdir()) else "run it without --resume")
        check_output(output, overwrite, inputs=guard)

    def prepare() -> None:
        if not main:
            return
        if stage.root.exists() and not resume:
            left = len(plan.units()) - len(stage.pending(plan)) if stage.plan_file.is_file() \
                else 0
            warn(f"an unfinished run of {output} ({left} frames) is discarded; --resume would "
                 "have continued it")
        _, before = prepare_stage(plan, output, resume)
        if before:
            typer.echo(f"resuming: {before} of {len(plan.units())} frames are done already")

    with joined(ranks):
        agreed(ranks, check)
        plan = agreed(ranks, lambda: make_plan(groups, folders, settings,
                                               warn if main else (lambda _: None)))
        agreed(ranks, prepare)
        reports = []
        try:
            with Progress(console=err, disable=not progress_enabled() or not main,
                          transient=True) as bar:
                if ranks.enabled:
                    share = plan.share(ranks.rank, ranks.world)
                    task = bar.add_task("deblurring", total=len(share))
                    reports = agreed(ranks, lambda: [run_share(
                        plan, stage, share, tick=lambda: bar.advance(task))])
                else:
                    pending = stage.pending(plan)
                    task = bar.add_task("deblurring", total=len(pending))
                    if jobs > 1 and len(pending) > 1:
                        reports = run_pool(plan, stage, pending, jobs, threads,
                                           tick=lambda: bar.advance(task))
                    else:
                        reports = [run_share(plan, stage, pending,
                                             tick=lambda: bar.advance(task))]
        except (KeyboardInterrupt, TrmdError):
            if main and stage.plan_file.is_file():
                warn(f"the frames finished so far are kept in {stage.root}: rerun with "
                     "--resume to finish")
            raise
        summary = agreed(ranks, lambda: finish(plan, stage, overwrite) if main else None)

    notes = ContrastNotes()
    for report in reports:
        for w in report.warnings:
            warn(w)
    for _, name, note, reliable in sorted(n for r in reports for n in r.contrast_notes):
        notes.add_note(name, note, reliable)
    for line in notes.lines():
        warn(line)
    mine = sum(r.frames for r in reports)
    if not main:
        typer.echo(f"rank {ranks.rank}: deblurred {mine} frames; rank 0 wrote {output}")
        return
    clipped = [s["clipped_fraction"] for s in summary]
    meta = plan.items[0].meta
    _report(summary, clipped, meta["method"], meta["n"], output, None, False)
    if len(plan.items) > 1:
        typer.echo(f"  from {len(plan.items)} recordings, one folder each")


def _report(summary: list[dict], clipped: list[float], method: str, n: int, output: Path,
            video: Path | None, single: bool) -> None:
    import numpy as np

    used = [s["contrast"] for s in summary if s["contrast"] is not None]
    auto = any(s["contrast_estimated"] for s in summary)
    if used:
        kind = "estimated" if auto else "given"
        if len(used) == 1:
            typer.echo(f"contrast threshold c = {used[0]:.3f} ({kind})")
        else:
            typer.echo(f"contrast threshold c ({kind}, per frame): median {np.median(used):.3f}, "
                       f"range {min(used):.3f}–{max(used):.3f}; each frame's value is in its "
                       "meta.json")
    from ..write import clipped_message

    said = clipped_message(float(np.mean(clipped)) if clipped else 0.0)
    if said:
        warn(said)
    passed = sum(s["passthrough"] for s in summary)
    frames = summary[0]["frames"] if summary else 2 * n + 1
    what = "1 frame" if single else f"{len(summary)} frames"
    extra = f" ({passed} passed through without events)" if passed else ""
    typer.echo(f"wrote {output}: {what} × {frames} latent frames ({method}, N={n}){extra}")
    if video is not None:
        typer.echo(f"wrote {video}")


def register(app: typer.Typer) -> None:
    app.command(name="deblur")(guarded(deblur))
