"""`trmd convert IN -o OUT.npz|.h5|.txt`: rewrite an event file in another format."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .boundary import guarded, warn
from .options import (
    Columns,
    ExposureLength,
    OneBased,
    Overwrite,
    Sensor,
    Stamp,
    TimeUnit,
    Topics,
    read_options,
)


def convert(
    source: Annotated[Path, typer.Argument(help="Event file to read.", readable=False)],
    output: Annotated[Path, typer.Option("--output", "-o",
                                         help="Output file: .npz, .h5 or .txt.", readable=False)],
    time_unit: TimeUnit = None,
    columns: Columns = None,
    one_based: OneBased = False,
    sensor: Sensor = None,
    exposure_length: ExposureLength = None,
    stamp: Stamp = None,
    topics: Topics = None,
    overwrite: Overwrite = False,
) -> None:
    """Convert events (and frames with exposure windows, for .h5) to npz, HDF5 or text."""
    from ..errors import InputError
    from ..read import open_events
    from ..read.hdf5 import HDF5Recording
    from ..read.paths import check_input_path
    from ..write import H5Writer, check_output, write_events_npz, write_events_text

    kind = output.suffix.lower()
    if kind not in (".npz", ".h5", ".hdf5", ".txt"):
        raise InputError(f"unknown output type {output.suffix!r}", path=output,
                         hint="use .npz, .h5 or .txt")
    check_input_path(source)
    with open_events(source, read_options(columns, one_based, time_unit, sensor,
                                          exposure_length, stamp, topics)) as rec:
        check_output(output, overwrite, inputs=[source])
        for w in rec.warnings:
            warn(w)
        n = rec.num_events()
        if n == 0:
            raise InputError("the recording holds no events: nothing to convert", path=source,
                             hint="check the file (trmd info), or a truncated copy")
        if isinstance(rec, HDF5Recording) and rec.has_ground_truth:
            warn("the simulator's ground truth (sharp frames, true contrast and camera path) is "
                 "not converted: `trmd eval` needs the original file")
        if kind in (".h5", ".hdf5"):
            with H5Writer(output, rec.width, rec.height) as w:
                for chunk in rec.iter_chunks():
                    w.add_events(chunk)
                skipped = 0
                for fr in rec.frames():
                    if fr.exposure is None:
                        skipped += 1
                        continue
                    if fr.image.shape[:2] != (rec.height, rec.width):
                        raise InputError(
                            f"frame {fr.name} is {fr.image.shape[1]}x{fr.image.shape[0]} but the "
                            f"sensor is {rec.width}x{rec.height}", path=source,
                            hint="convert to .npz (events and windows only) instead")
                    w.add_frame(fr.image, fr.exposure)
                windows = rec.stored_windows()
                if windows:
                    w.add_windows(windows)
                if skipped:
                    warn(f"{skipped} frame(s) without an exposure window were not converted "
                         "(the trmd HDF5 layout stores frames with their windows)")
        else:
            stream = rec.events()
            windows = rec.frame_exposures() or rec.stored_windows()
            if kind == ".npz":
                frames = len(rec.frame_exposures())
                if frames:
                    warn(f"npz output keeps events and exposure windows; the {frames} frame(s) "
                         "are dropped (convert to .h5 to keep them)")
                write_events_npz(output, stream, windows)
            else:
                if windows:
                    warn("text output keeps events only; exposure windows are dropped")
                write_events_text(output, stream)
    typer.echo(f"wrote {output}: {n} events")


def register(app: typer.Typer) -> None:
    app.command(name="convert")(guarded(convert))
