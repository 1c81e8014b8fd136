"""`trmd info FILE`: what is in an event file, or in a TRMD weights file."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from .boundary import guarded, warn
from .options import (
    Columns,
    ExposureLength,
    OneBased,
    Sensor,
    Stamp,
    TimeUnit,
    Topics,
    read_options,
)


def info(
    file: Annotated[Path, typer.Argument(
        help="Event file (txt, npz, npy, h5, aedat, aedat4, raw, dat, mat, ROS bag), an RPG "
             "folder, or TRMD weights (.safetensors).", readable=False)],
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False,
    time_unit: TimeUnit = None,
    columns: Columns = None,
    one_based: OneBased = False,
    sensor: Sensor = None,
    exposure_length: ExposureLength = None,
    stamp: Stamp = None,
    topics: Topics = None,
) -> None:
    """Describe an event file: format, events, sensor, duration, rate, polarity, frames.

    Given TRMD weights (.safetensors): architecture, parameters, what the network needs, the
    recipe and data it was trained on, and its validation figures; given the fusion network's
    weights: its size, training set and held-out figures.
    """
    from ..read.paths import check_input_path

    check_input_path(file)
    if file.suffix.lower() == ".safetensors":
        _weights_info(file, as_json)
        return
    from ..read import open_events
    from ..read.bins import describe_bins, is_bins_file
    from ..summary import summarize

    if is_bins_file(file):
        s = describe_bins(file)
        typer.echo(json.dumps(s, indent=2) if as_json else
                   "\n".join(f"{k.replace('_', ' ')}: {v}" for k, v in s.items()))
        return
    with open_events(file, read_options(columns, one_based, time_unit, sensor,
                                        exposure_length, stamp, topics)) as rec:
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


def _fusion_info(file: Path, as_json: bool) -> None:
    from ..models.fusion import describe_fusion

    d = describe_fusion(file)
    if as_json:
        typer.echo(json.dumps(d, indent=2))
        return
    from rich.console import Console
    from rich.table import Table

    t = Table(title=str(file), show_header=False, title_justify="left")
    t.add_row("weights", f"{d['weights']}, {d['parameters']:,} parameters, width "
                         f"{d['width']}, {d['size_kib']} KiB, sha256 {d['sha256']}")
    if d["trained_on"]:
        t.add_row("trained on", f"{d['trained_on']}, {d['steps']} steps")
    held = d["held_out_psnr"] or {}
    for i, (m, v) in enumerate(held.items()):
        t.add_row("held out" if i == 0 else "",
                  f"{m}: PSNR {v[0]:.2f} / {v[1]:.2f} dB (middle / sequence)")
    Console().print(t)


def _weights_info(file: Path, as_json: bool) -> None:
    from ..models.fusion import is_fusion_file
    from ..models.weights import describe_weights

    if is_fusion_file(file):
        _fusion_info(file, as_json)
        return
    d = describe_weights(file)
    if as_json:
        typer.echo(json.dumps(d, indent=2))
        return
    from rich.console import Console
    from rich.table import Table

    t = Table(title=str(file), show_header=False, title_justify="left")
    name = d["architecture"] + (f" (recorded as {d['recorded_as']})" if d["recorded_as"] else "")
    t.add_row("weights", f"{name}, {d['parameters']:,} parameters, {d['dtype']}, "
                         f"{d['size_mib']} MiB, sha256 {d['sha256']}")
    if d["checkpoint"]:
        ck = d["checkpoint"]
        t.add_row("checkpoint", f"step {ck.get('step')} of a training run; its "
                                f"{'weight average' if ck.get('weights') == 'ema' else 'model'} "
                                "is what deblur, hfr and eval use")
    t.add_row("frames", f"N = {d['n']} ({2 * int(d['n']) + 1} latent frames), "
                        f"{d['channels']} channel(s)")
    for i, need in enumerate(d["inputs"]):
        t.add_row("needs" if i == 0 else "", need)
    t.add_row("recipe", str(d["recipe"]))
    if d["training_data"]:
        t.add_row("trained on", ", ".join(map(str, d["training_data"])))
    val = d["validation"] or {}
    rows = [(m, v) for m, v in val.items() if isinstance(v, dict) and "psnr_mid" in v]
    for i, (m, v) in enumerate(rows):
        t.add_row("validation" if i == 0 else "",
                  f"{m}: PSNR {v['psnr_mid']:.2f} / {v['psnr_seq']:.2f} dB (middle / sequence)"
                  + (f", SSIM {v['ssim_mid']:.3f} / {v['ssim_seq']:.3f}" if "ssim_mid" in v
                     else ""))
    if rows and val.get("set"):
        t.add_row("", f"on {val['set']}")
    ft = d["finetune"]
    if ft:
        t.add_row("fine-tuned on", f"{', '.join(map(str, ft.get('inputs', [])))}: "
                                   f"{ft.get('windows')} window(s), {ft.get('steps')} steps, "
                                   f"from weights {ft.get('init_weights')}")
        before, after = ft.get("held_out_before") or {}, ft.get("held_out_after") or {}
        if "total" in before and "total" in after:
            t.add_row("", f"held-out loss {before['total']:.4g} → {after['total']:.4g} "
                          f"({ft.get('held_out')} window(s))")
    Console().print(t)


def register(app: typer.Typer) -> None:
    app.command(name="info")(guarded(info))
