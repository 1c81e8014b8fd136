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

import contextlib
import math
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Annotated

import typer

from .boundary import as_flags, err, guarded, progress_enabled, warn
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

#: a literal so --help need not import the methods; a test keeps it equal to
#: methods.DEFAULT_METHOD
_DEFAULT_METHOD_HELP = "fused"

Method = Annotated[str | None, typer.Option(
    "--method", help="edi (model-based, no weights), trmd (learned residuals), motion "
    "(deconvolution along the events' global motion, guarded by EDI) or fused (trmd and "
    "motion fused by a small trained network). "
    f"Default: {_DEFAULT_METHOD_HELP}.")]
NOpt = Annotated[int | None, typer.Option(
    "--n", min=1, max=16, help="Latent frames 2N+1 per exposure (default 3 → 7 frames; TRMD: "
    "the weights' N).")]
Contrast = Annotated[str, typer.Option(
    "--contrast", help="Event contrast threshold c (used by EDI and by TRMD); 'auto': estimate "
    "one for the recording from its busiest frames; 'frame': estimate it for every frame.")]
TimeOffset = Annotated[str | None, typer.Option(
    "--time-offset", help="Shift the exposure window(s) relative to the events, e.g. -40ms "
    "(real DAVIS data often needs tens of ms; a number without a unit is µs).")]
Weights = Annotated[Path | None, typer.Option("--weights", help="RE-Net weights "
                                                 "(.safetensors) for trmd and fused; without "
                                                 "--method it implies one of them. Default: "
                                                 "the shipped weights.", readable=False)]
HotPixels = Annotated[bool, typer.Option("--hot-pixels/--keep-hot-pixels",
                                         help="Ignore the events of hot pixels (default on).")]
Isolated = Annotated[bool, typer.Option(
    "--drop-isolated/--keep-isolated",
    help="Leave out of EDI (its frames, the threshold's estimate, the priors it gives the "
         "other methods) the events no neighbouring pixel corroborates within 1/16 of the "
         "exposure: the sensor's background activity, which EDI turns into speckle (default "
         "on; the networks' inputs keep every event).")]
Pattern = Annotated[bool, typer.Option(
    "--remove-pattern/--keep-pattern",
    help="Remove the APS sensor's fixed pattern (each pixel's own offset, the same in every "
         "frame) from the blurry frames before deblurring: estimated over up to 16 of the "
         "recording's frames, and only where the scene moves between them and they agree on "
         "one (default on; a single frame or a still camera keeps its frames as they are).")]
BitDepth = Annotated[int, typer.Option("--bit-depth", help="PNG bit depth: 8 or 16.")]
Jobs = Annotated[str, typer.Option(
    "--jobs", "-j", help="Worker processes on this machine, each on its share of the frames "
    "(torch threads per worker: the cores shared out, unless --threads). auto (the "
    "default): for the motion and fused methods one per core, each with at least the work of "
    "four 346x260 frames, at most 8, and 1.5 GB of free memory each; else one. Across "
    "machines, "
    "launch the command with torchrun instead: each rank takes frames rank, rank + world, …; "
    "rank 0 writes meta.json and the output once every rank is done.")]
Resume = Annotated[bool, typer.Option(
    "--resume", help="Continue an unfinished run of this output (interrupted, or a rank that "
    "failed): the frames already complete are kept, the rest deblurred. Runs with --jobs, "
    "torchrun, several recordings or --resume keep finished frames in .OUT.trmd-partial "
    "beside -o until the output is swapped in whole.")]


def parse_contrast(text: str) -> float | None:
    """``"auto"`` or ``"frame"`` → None (estimated); a positive number → float."""
    from ..errors import InputError

    if text.strip().lower() in ("auto", "frame"):
        return None
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"--contrast {text!r} is not a number, 'auto' or 'frame'",
                         hint="e.g. --contrast 0.25, or --contrast auto") from None
    if not (value > 0 and value < 10):
        raise InputError(f"--contrast {text} must be a positive number below 10 "
                         "(typically 0.1–0.5)",
                         hint="e.g. --contrast 0.25, or --contrast auto")
    return value


def contrast_scope(text: str) -> str:
    """What an estimated c is estimated over: ``--contrast frame`` → "frame", else
    "recording"."""
    return "frame" if text.strip().lower() == "frame" else "recording"


#: the methods that run RE-Net weights (``--weights``)
_TAKE_WEIGHTS = ("trmd", "fused")


def choose_method(method: str | None, weights: Path | None, default: str) -> str:
    """The method to run: ``--weights`` without ``--method`` means the default when it runs
    RE-Net, else TRMD (a damaged weights file is never ignored without a word); with
    ``--method edi`` it is ignored with a warning."""
    if method is None:
        return default if weights is None or default in _TAKE_WEIGHTS else "trmd"
    if weights is not None and method.lower() not in _TAKE_WEIGHTS:
        warn(f"--weights is ignored: --method is {method}")
    return method.lower()


def method_config(method: str | None, weights: Path | None, n: int | None, contrast: str,
                  hot_pixels: bool, device: str, threads: int | None, bit_depth: int,
                  precision: str = "auto", settle_contrast: bool = False,
                  drop_isolated: bool = True, fixed_pattern: bool = True):
    """The options deblur and hfr share, checked and turned into a ``MethodConfig``."""
    from ..errors import InputError
    from ..methods import DEFAULT_METHOD, MethodConfig

    config = MethodConfig(method=choose_method(method, weights, DEFAULT_METHOD), n=n,
                          contrast=parse_contrast(contrast),
                          contrast_scope=contrast_scope(contrast), hot_pixels=hot_pixels,
                          drop_isolated=drop_isolated, fixed_pattern=fixed_pattern,
                          weights=weights, device=device,
                          threads=threads, precision=precision,
                          settle_contrast=settle_contrast)
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
) -> None:
    """Deblur: write 2N+1 sharp frames per blurry frame, plus sharp.png, timestamps.txt and
    meta.json (method, N, c used, weights hash, inputs).

    Several recordings (REC1 REC2 …, or a folder of .h5/.aedat4/.aedat/.bag files and
    recording folders) go to one sub-folder each, named after the recording. The output is
    written whole at the end; runs that share frames out (--jobs, torchrun) or may be resumed
    keep the finished frames in .OUT.trmd-partial beside it meanwhile. With the same --threads
    the result is the same file for file as a run in one process (on other thread counts the
    trmd and fused methods' network may round a few pixels to the next grey level)."""
    from ..batch import (
        choose_jobs,
        count_work,
        discard_stage,
        frame_folder_name,
        ranks_from_env,
        recordings_in,
        run_meta,
        staged,
    )
    from ..deblur import ContrastNotes, binned_note, deblur_frames, settle
    from ..errors import InputError
    from ..methods import make_method
    from ..overlap import ahead
    from ..read.inputs import open_inputs
    from ..video import VIDEO_SUFFIXES, VideoWriter, check_fps, check_video_path
    from ..write import atomic_dir, check_output, write_json, write_result_folder

    # every option is checked before any file is opened or written
    requested_jobs = parse_jobs(jobs)
    recordings = recordings_in(inputs)
    if len(inputs) > 2 and recordings is None:
        raise InputError(f"deblur takes one or two inputs, got {len(inputs)}",
                         hint="for several images use a frames folder, or `trmd hfr`")
    config = method_config(method, weights, n, contrast, hot_pixels, device, threads,
                           bit_depth, precision, drop_isolated=drop_isolated,
                           fixed_pattern=remove_pattern)
    if video is not None and not (math.isfinite(fps) and fps > 0):
        raise InputError(f"--fps must be a positive number, got {fps}", hint="e.g. --fps 10")
    offset = parse_duration_us(time_offset) if time_offset else 0
    opts = read_options(columns, one_based, time_unit, sensor, exposure_length, stamp, topics)
    if output.suffix.lower() in VIDEO_SUFFIXES and not output.is_dir():
        # a folder named like a video would surprise whoever opens it in a player
        raise InputError("-o names a video, but deblur writes a folder of frames", path=output,
                         hint=f"use -o FOLDER --video {output.name}, or `trmd hfr -o "
                         f"{output.name}`")
    ranks = ranks_from_env()
    jobs = choose_jobs(requested_jobs, config, lambda: count_work(
        inputs, recordings, opts, exposure, offset), ranks=ranks, in_order=video is not None)
    if staged(jobs, resume, ranks, recordings):
        from ..batch import Settings, make_plan, run_staged

        if video is not None:
            raise InputError("--video needs every frame in order in one process: not with "
                             "--jobs, --resume, torchrun or several recordings",
                             hint="leave out --video, and make one afterwards with `trmd hfr`")
        settings = Settings(config, opts, None if exposure is None else tuple(exposure),
                            offset, bit_depth, compare)
        run = run_staged(make_plan, inputs, recordings, settings, output, ranks=ranks,
                         jobs=jobs, resume=resume, overwrite=overwrite,
                         guard=[*inputs, weights], warn=warn, say=typer.echo,
                         progress=progress_bar)
        if run.main:
            meta = run.plan.items[0].meta
            _report(run.summary, meta["method"], meta["n"], output, None, False,
                    [it.settled for it in run.plan.items])
            if len(run.plan.items) > 1:
                typer.echo(f"  from {len(run.plan.items)} recordings, one folder each")
        return
    check_output(output, overwrite, inputs=[*inputs, weights], folder=True)
    if video is not None:
        check_video_path(video)
        check_fps(video, fps)
        # a video inside the output folder would go with the folder it replaces
        check_output(video, overwrite, inputs=[*inputs, weights])
        if output.resolve() in video.resolve().parents:
            raise InputError("--video is inside the -o folder, which deblur replaces whole",
                             path=video, hint="write the video beside the folder")

    with open_inputs(inputs, opts, exposure=exposure, offset_us=offset) as ins:
        for w in ins.warnings:
            warn(w)
        discard_stage(output, warn)
        est, settled = settle(make_method(config), ins.source, config)
        meta = run_meta(ins, est, config, offset, bit_depth, settled)
        said = [binned_note(ins.source, est)] if ins.binned else []
        summary: list[dict] = []
        notes = ContrastNotes()
        vw = VideoWriter(video, fps) if video is not None else None
        try:
            with atomic_dir(output) as tmp, progress_bar("deblurring", len(ins.source),
                                                         shown=not ins.single) as tick:
                # the next frame is deblurred while this one is written (closed here, not
                # whenever the collector gets to it, when writing fails)
                with contextlib.closing(ahead(deblur_frames(ins.source, est))) as results:
                    for res in results:
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
                        if vw is not None:
                            for img in res.frames:
                                vw.append(img)
                        tick()
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
    _report(summary, est.name, est.n, output, video, ins.single, [settled])


@contextlib.contextmanager
def progress_bar(label: str, total: int, shown: bool = True) -> Iterator[Callable[[], None]]:
    """A progress bar on stderr (on a terminal, unless not ``shown``) of ``total`` steps, gone
    when done; gives the function that advances it one step."""
    from rich.progress import Progress

    with Progress(console=err, disable=not progress_enabled() or not shown,
                  transient=True) as bar:
        task = bar.add_task(label, total=total)
        yield lambda: bar.advance(task)


def _report(summary: list[dict], method: str, n: int, output: Path, video: Path | None,
            single: bool, recordings: Sequence) -> None:
    """``recordings``: what was settled for each recording (a ``Settled``) or None."""
    import numpy as np

    for done in recordings:
        for line in [] if done is None else done.lines():
            typer.echo(as_flags(line))
    settled = [d for d in recordings if d is not None and d.contrast is not None]
    used = [s["contrast"] for s in summary if s["contrast"] is not None]
    auto = any(s["contrast_estimated"] for s in summary)
    default = any(s.get("contrast_default", False) for s in summary)
    if used and len(settled) < len(recordings):
        kind = "estimated" if auto else \
            "the default: too few events to estimate it" if default else "given"
        if len(used) == 1:
            typer.echo(f"contrast threshold c = {used[0]:.3f} ({kind})")
        elif len(set(used)) == 1:
            typer.echo(f"contrast threshold c = {used[0]:.3f} ({kind}) for every frame")
        else:
            typer.echo(f"contrast threshold c ({kind}, per frame): median {np.median(used):.3f}, "
                       f"range {min(used):.3f}–{max(used):.3f}; each frame's value is in its "
                       "meta.json")
    from ..write import clipped_message

    clipped = [s["clipped_fraction"] for s in summary]
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
