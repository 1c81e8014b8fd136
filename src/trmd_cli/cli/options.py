"""Options shared by several commands (Annotated types) and their parsers."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Optional

import typer

from ..errors import InputError
from ..read.base import ReadOptions

__all__ = [
    "N", "Exposure", "Sensor", "TimeUnit", "Columns", "OneBased", "Overwrite", "Device",
    "Threads", "read_options", "parse_sensor", "parse_duration_us", "ExposureLength", "Stamp",
    "Topics", "parse_exposure_length_us",
]

N = Annotated[int, typer.Option("--n", min=1, max=16,
                                help="Latent frames 2N+1 per exposure (N=3 → 7 frames).")]
Exposure = Annotated[
    Optional[tuple[float, float]],
    typer.Option("--exposure", help="Exposure window T0 T1, in --time-unit if given; else "
                 "numbers with a fraction are seconds and whole numbers are in the unit of "
                 "the file's times (seconds for a file of float seconds, else µs). Overrides "
                 "frames or windows stored in the file."),
]
Sensor = Annotated[Optional[str], typer.Option("--sensor", help="Sensor size WxH, e.g. 346x260, "
                                               "for files that store none.")]
TimeUnit = Annotated[Optional[str], typer.Option(
    "--time-unit", help="Unit of the file's times: s, ms, us or ns (default: integers are µs, "
    "floats are seconds; times are kept in whole µs, ns floored to them).")]
Columns = Annotated[Optional[str], typer.Option(
    "--columns", help="Text column order, e.g. t,y,x,p (default t,x,y,p).")]
OneBased = Annotated[bool, typer.Option("--one-based", help="Coordinates count from 1.")]
Overwrite = Annotated[bool, typer.Option("--overwrite", help="Replace an existing output.")]
Device = Annotated[str, typer.Option("--device", help="auto, cpu or cuda.")]
Threads = Annotated[Optional[int], typer.Option(
    "--threads", min=1,
    help="CPU threads: torch's, and the motion method's (1: no helper process) (default: all).")]
ExposureLength = Annotated[Optional[str], typer.Option(
    "--exposure-length", help="Exposure time of every frame, with its unit (20ms, 500us, "
    "0.02s), for ROS bags without exposure messages and RPG folders, whose frames carry one "
    "time stamp each.")]
Stamp = Annotated[Optional[str], typer.Option(
    "--stamp", help="What a frame's time stamp marks in ROS bags and RPG folders: start "
    "(default) or middle of its exposure (rpg_dvs_ros stamps the middle).")]
Topics = Annotated[Optional[str], typer.Option(
    "--topics", help="ROS bag topics to read, comma-separated: the events, and the images and "
    "their exposure times if wanted, e.g. /dvs/events,/dvs/image_raw (default: chosen by "
    "message type).")]
Precision = Annotated[str, typer.Option(
    "--precision", help="The network's arithmetic: auto (bfloat16 on CPUs with AMX / "
    "AVX512-BF16, float16 on CUDA, else float32), fp32, bf16 or fp16.")]

_UNIT_US = {"s": 1e6, "ms": 1e3, "us": 1.0, "µs": 1.0, "ns": 1e-3}


def parse_sensor(text: str | None, option: str = "--sensor") -> tuple[int, int] | None:
    """``"346x260"`` → (346, 260); ``option``: the flag the text came from, for messages."""
    if text is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*[xX×,]\s*(\d+)\s*", text)
    if not m or int(m[1]) == 0 or int(m[2]) == 0:
        raise InputError(f"{option} {text!r} is not WxH", hint="write it like 346x260")
    return int(m[1]), int(m[2])


def parse_jobs(text: str) -> int | None:
    """``--jobs``: ``"auto"`` → None (the run chooses); a whole number ≥ 1 → that number."""
    if text.strip().lower() == "auto":
        return None
    if not re.fullmatch(r"\s*[-+]?\d+\s*", text):
        raise InputError(f"--jobs must be a whole number or auto, got {text!r}",
                         hint="e.g. --jobs 4 (one worker process per core), or --jobs auto")
    jobs = int(text)
    if jobs < 1:
        raise InputError(f"--jobs must be at least 1, got {jobs}",
                         hint="e.g. --jobs 4 (one worker process per core)")
    return jobs


def parse_duration_us(text: str) -> int:
    """``"-40ms"``, ``"1.5s"``, ``"250us"`` → integer µs, exactly (no float in between). A bare
    number is µs; a duration that is not a whole number of µs is refused, never rounded."""
    return _exact_us(text, "", signed=True, example="write it like -40ms, 1.5s or 250us",
                     whole_hint="event times are whole µs: give the unit, e.g. -40ms, "
                                "-0.004s or -4000us")


def parse_exposure_length_us(text: str | None) -> int | None:
    """``"20ms"``, ``"500us"``, ``"0.02s"`` → whole µs (exact: no float in between); the unit is
    required, a fraction of a microsecond refused."""
    if text is None:
        return None
    example = "e.g. --exposure-length 20ms (or 500us, 0.02s)"
    us = _exact_us(text, "--exposure-length ", signed=False, example=example,
                   whole_hint="event times are whole µs: give e.g. 20ms or 20001us")
    if us <= 0:
        raise InputError(f"--exposure-length {text} is not positive", hint=example)
    return us


def _exact_us(text: str, flag: str, *, signed: bool, example: str, whole_hint: str) -> int:
    """A duration with its unit (s, ms, us, ns) → whole µs through decimal arithmetic, never
    rounded. ``signed``: a sign and an exponent are allowed, and a bare number is µs; else the
    unit is required. ``flag`` (with its space) begins the messages."""
    from decimal import Decimal, InvalidOperation

    number = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?" if signed else \
        r"\d+(?:\.\d*)?|\.\d+"
    m = re.fullmatch(rf"\s*({number})\s*(s|ms|us|µs|ns)?\s*", text)
    if not m:
        raise InputError(f"{flag}{text!r} is not a duration", hint=example)
    if m[2] is None and not signed:
        raise InputError(f"{flag}{text!r} needs its unit", hint=example)
    scale = {"s": 1_000_000, "ms": 1_000, "us": 1, "µs": 1, "ns": Decimal("0.001")}[m[2] or "us"]
    try:
        us = Decimal(m[1]) * scale
    except InvalidOperation:
        raise InputError(f"{flag}{text!r} is not a duration", hint=example) from None
    if abs(us) >= 2**62:
        raise InputError(f"{flag}{text!r} is out of range", hint=example)
    if us != us.to_integral_value():
        bare = " (a number without a unit is µs)" if m[2] is None else ""
        raise InputError(f"{flag}{text.strip()} is {us.normalize():f} µs{bare}, not a whole "
                         "number of microseconds", hint=whole_hint)
    return int(us)


def read_options(columns: str | None = None, one_based: bool = False,
                 time_unit: str | None = None, sensor: str | None = None,
                 exposure_length: str | None = None, stamp: str | None = None,
                 topics: str | None = None) -> ReadOptions:
    cols = None
    if columns:
        cols = tuple(c.strip().lower() for c in columns.split(","))
        if sorted(c for c in cols if c != "_") != ["p", "t", "x", "y"]:
            raise InputError(f"--columns {columns!r} must name t, x, y and p once each "
                             "(use _ to skip a column)", hint="e.g. --columns t,y,x,p")
    if time_unit is not None and time_unit not in _UNIT_US:
        raise InputError(f"--time-unit {time_unit!r} is not one of s, ms, us, ns",
                         hint="e.g. --time-unit us")
    if stamp is not None and stamp.strip().lower() not in ("start", "middle"):
        raise InputError(f"--stamp {stamp!r} is neither start nor middle",
                         hint="e.g. --stamp middle (the default is start)")
    names = None
    if topics is not None:
        names = tuple(t.strip() for t in topics.split(",") if t.strip())
        if not names:
            raise InputError(f"--topics {topics!r} names no topic",
                             hint="e.g. --topics /dvs/events,/dvs/image_raw")
    return ReadOptions(columns=cols, one_based=one_based,
                       time_unit=None if time_unit is None else time_unit.replace("µs", "us"),
                       sensor=parse_sensor(sensor),
                       exposure_length_us=parse_exposure_length_us(exposure_length),
                       stamp=None if stamp is None else stamp.strip().lower(), topics=names)


def existing(path: Path) -> Path:
    if not path.exists():
        raise InputError("file not found", path=path, hint="check the path")
    return path
