"""`trmd motion`: the global motion the events show, as pictures and numbers.

Inputs as for ``trmd deblur`` (:func:`trmd_cli.read.inputs.open_inputs`); per frame it writes
flow.png, weight.png, events.png and motion.json (:mod:`trmd_cli.motion_views`,
:mod:`trmd_cli.viz`), flat into OUT/ for one blurry image, else one sub-folder per frame.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .boundary import as_flags, err, guarded, progress_enabled, warn
from .deblur import (
    Contrast,
    HotPixels,
    Isolated,
    Pattern,
    TimeOffset,
    contrast_scope,
    parse_contrast,
)
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

#: what every frame's folder holds, for the closing line
FILES = ("flow.png", "weight.png", "events.png", "motion.json")


def motion(
    inputs: Annotated[list[Path], typer.Argument(
        help="BLURRY EVENTS, or RECORDING, or IMAGES_DIR EVENTS|EVENTS_DIR (as for deblur; "
             "binned events have no times to find a motion in).",
        show_default=False, readable=False)],
    output: Annotated[Path, typer.Option("--output", "-o", help="Output folder.", readable=False)],
    exposure: Exposure = None,
    contrast: Contrast = "auto",
    time_offset: TimeOffset = None,
    hot_pixels: HotPixels = True,
    drop_isolated: Isolated = True,
    remove_pattern: Pattern = True,
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
    """Show the global motion `deblur --method motion` finds in each exposure's events:
    flow.png (each pixel's displacement over the exposure, hue = direction, saturation =
    length, colour-wheel legend with its scale), weight.png (where the deconvolution is used:
    white; where EDI is: black), events.png (the events as recorded | carried to mid-exposure
    by the motion: the sharper, the better the motion) and motion.json (velocity in px per
    exposure and per second, acceleration, jerk, rotation, zoom, perspective, confidence, with
    units)."""
    from rich.progress import Progress

    from .. import __version__
    from ..batch import frame_folder_name
    from ..errors import InputError
    from ..motion_views import motion_summary, motion_views
    from ..read.inputs import open_inputs
    from ..viz import event_picture, flow_picture, weight_picture
    from ..write import atomic_dir, check_output, write_image, write_json

    if len(inputs) > 2:
        raise InputError(f"motion takes one or two inputs, got {len(inputs)}",
                         hint="for several images use a frames folder")
    c = parse_contrast(contrast)
    offset = parse_duration_us(time_offset) if time_offset else 0
    check_output(output, overwrite, inputs=inputs, folder=True)
    if threads is not None:
        import torch

        torch.set_num_threads(threads)
    with open_inputs(inputs, read_options(columns, one_based, time_unit, sensor,
                                          exposure_length, stamp, topics),
                     exposure=exposure, offset_us=offset) as ins:
        if ins.binned:
            raise InputError("binned events have no event times to find a motion in",
                             path=inputs[-1], hint="give the raw events (an event file or a "
                             "recording)")
        for w in ins.warnings:
            warn(w)
        # as `trmd deblur` settles them: the fixed pattern, then one c for the recording
        # (here also from a single frame, which then reports where its c came from)
        from ..deblur import pattern_line, recording_contrast, recording_line, recording_pattern
        from ..methods import EdiMethod

        edi = EdiMethod(3, c, hot_pixels, drop_isolated=drop_isolated)
        pattern = recording_pattern(ins.source) if remove_pattern else None
        if pattern is not None:
            typer.echo(as_flags(pattern_line(pattern)))
            edi = edi.for_pattern(pattern)
        if c is None and contrast_scope(contrast) == "recording":
            rec = recording_contrast(ins.source, hot_pixels=hot_pixels,
                                     drop_isolated=drop_isolated, pattern=pattern)
            if rec is not None:
                typer.echo(as_flags(recording_line(rec)))
                edi = edi.for_recording(rec)
        written: list[str] = []
        with atomic_dir(output) as tmp, Progress(
                console=err, disable=not progress_enabled() or ins.single,
                transient=True) as bar:
            task = bar.add_task("estimating motion", total=len(ins.source))
            for win in ins.source:
                f, e = win.frame, win.frame.exposure
                if len(win.events.slice(e.start_us, e.end_us + 1)) == 0:
                    warn(f"frame {f.name}: no events in its exposure window [{e.start_us}, "
                         f"{e.end_us}] µs; skipped")
                    bar.advance(task)
                    continue
                views = motion_views(f.image, win.events, e, edi=edi)
                folder = tmp
                if not ins.single:
                    folder = tmp / frame_folder_name(f.name, f.index)
                    folder.mkdir()
                write_image(folder / "flow.png", flow_picture(views.displacement))
                write_image(folder / "weight.png", weight_picture(views.weight))
                write_image(folder / "events.png", event_picture(
                    [views.events_before, views.events_after],
                    ["as recorded", "motion-compensated"]))
                summary = motion_summary(views)
                write_json(folder / "motion.json", {"tool": f"trmd {__version__}",
                                                     "frame": f.name, "inputs": ins.paths,
                                                     "time_offset_us": offset, **summary})
                for note in views.notes:
                    warn(f"frame {f.name}: {note}")
                typer.echo(_line(f.name, summary))
                written.append(f.name)
                bar.advance(task)
            if not written:
                raise InputError("no frame has events in its exposure window",
                                 hint="check the inputs, or move the windows with "
                                 "--time-offset")
    what = "1 frame" if ins.single else f"{len(written)} frames"
    typer.echo(f"wrote {output}: {what} ({', '.join(FILES)})")


def _line(name: str, s: dict) -> str:
    vx, vy = s["velocity_px_per_exposure"]
    if not s["motion_found"]:
        return (f"{name}: no clear global motion in the events (confidence "
                f"{s['confidence']:.2f}): EDI's frames are used; the search's best candidate "
                f"(velocity ({vx:.2f}, {vy:.2f}) px per exposure) is in motion.json")
    return (f"{name}: velocity ({vx:.2f}, {vy:.2f}) px per exposure, direction "
            f"{s['direction_deg']:.1f}°, rotation {s['rotation_deg_per_exposure']:.3f}°, "
            f"zoom {100 * s['zoom_log_scale_per_exposure']:.2f} %, pixels travel up to "
            f"{s['start_to_end_px']['max']:.1f} px; confidence {s['confidence']:.2f}, "
            f"deconvolution used on {100 * s['deconvolution_share']:.0f} % of the frame")


def register(app: typer.Typer) -> None:
    app.command(name="motion")(guarded(motion))
