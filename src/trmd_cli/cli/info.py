"""`trmd info FILE`: what is in an event file."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from .boundary import guarded, warn
from .options import Columns, OneBased, Sensor, TimeUnit, read_options


def info(
    file: Annotated[Path, typer.Argument(
        help="Event file (txt, npz, npy, h5, aedat4, raw, dat, mat).")],
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False,
    time_unit: TimeUnit = None,
    columns: Columns = None,
    one_based: OneBased = False,
    sensor: Sensor = None,
) -> None:
    """Describe an event file: format, events, sensor, duration, rate, polarity, frames."""
    from ..read import open_events
    from ..summary import summarize

    with open_events(file, read_options(columns, one_based, time_unit, sensor)) as rec:
        for w in rec.warnings:
            warn(w)
        s = summarize(rec)
    if s["events"] == 0:
        warn(f"{file} holds no events (an empty or cut-short recording?)")
    if as_json:
        typer.echo(json.dumps(s, indent=2))
        return
    from rich.console import Console
    from rich.table import Table

    t = Table(title=str(file), show_header=False, title_justify="left")
    for k, v in s.items():
        if k == "frames":
            continue
        t.add_row(k.replace("_", " "), str(v))
    frames = s.get("frames") or []
    if frames:
        t.add_row("frames", str(len(frames)))
        for fr in frames[:5]:
            t.add_row("", f"#{fr['index']}: exposure {fr['start_us']}..{fr['end_us']} µs "
                          f"({fr['duration_ms']:.3f} ms), {fr['events']} events")
        if len(frames) > 5:
            t.add_row("", f"… {len(frames) - 5} more (--json lists all)")
    Console().print(t)


def register(app: typer.Typer) -> None:
    app.command(name="info")(guarded(info))
