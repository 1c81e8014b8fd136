"""Text event files, one event per line.

Accepted layouts (columns default to ``t x y p``; ``columns`` reorders, ``_`` skips one):
- ECD style: ``t x y p`` with t in float seconds;
- E2VID style: a first line ``W H`` (sensor size), then events;
- EVDI style: integer microseconds;
- header lines (non-numeric) and ``#`` comments are skipped; separators are blanks or commas.
Time unit: a t column written with a decimal point or exponent is seconds, integers are µs,
unless ``time_unit`` says otherwise. Polarity 0/−1 = OFF, 1 = ON.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..events import make_stream
from .base import MemoryRecording, ReadOptions
from .units import collapsed_times, to_microseconds

__all__ = ["read_text", "parse_text_events"]

_NUM = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")


def _split(line: str) -> list[str]:
    return [f for f in re.split(r"[,\s;]+", line.strip()) if f]


def _is_numeric(fields: list[str]) -> bool:
    return bool(fields) and all(_NUM.match(f) for f in fields)


def read_text(path: Path, options: ReadOptions) -> MemoryRecording:
    """Read a text event file into memory (numpy's C parser, several M events/s)."""
    with open(path, encoding="utf-8", errors="replace") as fh:
        head = [fh.readline() for _ in range(64)]
    skip, sensor, warnings = 0, options.sensor, []
    first_data = None
    for i, line in enumerate(head):
        fields = _split(line.split("#", 1)[0])
        if not fields:
            skip = i + 1
            continue
        if not _is_numeric(fields):  # a header such as "t,x,y,p"
            skip = i + 1
            continue
        if len(fields) == 2 and first_data is None and i == skip:
            # E2VID: "W H" on the first line
            if sensor is None:
                w, h = (float(f) for f in fields)
                if not (w.is_integer() and h.is_integer() and 0 < w <= 65535 and 0 < h <= 65535):
                    raise FormatError(f"the first line '{' '.join(fields)}' is not a sensor size "
                                      "W H", path=path,
                                      hint="fix that line or pass `sensor=(W, H)`")
                sensor = (int(w), int(h))
            skip = i + 1
            continue
        first_data = fields
        break
    if first_data is None:
        raise FormatError("no event lines found (truncated, or not an event file?)", path=path,
                          hint="expected lines like '0.000123 45 67 1' (t x y p)")
    columns = options.columns or ("t", "x", "y", "p")
    if len(first_data) < len(columns):
        raise FormatError(f"event lines have {len(first_data)} columns, expected "
                          f"{len(columns)} ({' '.join(columns)})", path=path,
                          hint="use `columns` to say which column is which")
    delim = "," if "," in head[skip] else None
    if delim is None and all(("  " not in ln and "\t" not in ln and not ln.startswith(" "))
                             for ln in head[skip:] if ln.strip()):
        delim = " "  # single spaces: pandas' fast path (a regex separator halves its speed)
    try:
        cols = _fast_parse(path, delim, skip, columns,
                           exact=len(first_data) == len(columns),
                           comments=any("#" in ln for ln in head[skip:]))
        if cols is None:
            data = np.loadtxt(path, comments="#", delimiter=delim, skiprows=skip, ndmin=2,
                              usecols=range(len(columns)), dtype=np.float64)
            cols = {name: data[:, i] for i, name in enumerate(columns) if name != "_"}
    except ValueError as e:
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        m = re.search(r"\b(line|row) (\d+)", msg)
        # numpy counts data rows from 0 after the skipped header
        where = "" if not m else f" near line {int(m[2]) + (skip + 1 if m[1] == 'row' else 0)}"
        raise FormatError(f"malformed event line{where}: {msg[:160]}", path=path,
                          hint="every line needs numbers t x y p; a short last line means the "
                               "copy is incomplete (copy it again, or delete that line)") from None
    t_field = first_data[columns.index("t")]
    unit = options.time_unit
    if unit is None:
        # the whole column decides: eSL-Net writes the first time as "0" and the rest as
        # fractions of a second, and one integer-looking row must not truncate them all
        tcol = cols["t"]
        with np.errstate(invalid="ignore"):  # a non-finite time is reported just below
            fractional = bool(len(tcol)) and not bool(np.all(np.mod(tcol, 1.0) == 0.0))
        unit = "s" if ("." in t_field or "e" in t_field.lower() or fractional) else "us"
    t = to_microseconds(cols["t"], unit)
    collapsed = collapsed_times(t, unit)
    if collapsed:
        warnings.append(collapsed)
    x, y = cols["x"], cols["y"]
    if options.one_based:
        x, y = x - 1, y - 1
    sensor = sensor or options.frame_size
    if sensor is None:
        warnings.append("the file stores no sensor size: using max+1 of the coordinates "
                        "(pass `sensor=(W, H)` to set it)")
    w, h = (None, None) if sensor is None else sensor
    try:
        stream = make_stream(x, y, t, cols["p"], w, h, source=str(path))
    except InputError as e:
        raise InputError(e.detail, path=path, hint=e.hint) from None
    return MemoryRecording(stream, path, "text", warnings=warnings)


def _fast_parse(path: Path, delim: str | None, skip: int, columns: tuple[str, ...], *,
                exact: bool = False, comments: bool = True) -> dict[str, np.ndarray] | None:
    """pandas' C parser when installed (2–3× numpy's, more with integer columns typed as
    such); None to fall back to numpy, which also names a malformed line better.

    ``comment`` and ``usecols`` each cost pandas ~50 %, so they are passed only when the sampled
    lines need them (``exact``: as many columns as names). A comment further down makes a typed
    column fail to parse, and numpy (which skips comments) takes over."""
    try:
        import pandas as pd
    except ImportError:
        return None
    use = [i for i, name in enumerate(columns) if name != "_"]
    typed = {i: (np.float64 if columns[i] == "t" else np.int64) for i in use}
    for dtype in (typed, np.float64):  # coordinates written as "12.0" need the second pass
        try:
            extra = {} if exact and len(use) == len(columns) else {"usecols": use}
            if comments:
                extra["comment"] = "#"
            frame = pd.read_csv(path, sep=r"\s+" if delim is None else delim, header=None,
                                skiprows=skip, dtype=dtype, engine="c", skip_blank_lines=True,
                                **extra)
        except Exception:  # noqa: BLE001 - try the next dtype, then numpy
            continue
        cols = {columns[i]: frame[i].to_numpy() for i in use}
        if any(c.dtype.kind == "f" and np.isnan(c).any() for c in cols.values()):
            return None  # a short line: let numpy report it
        return cols
    return None


def parse_text_events(text: str, options: ReadOptions | None = None):
    """Parse events from a string (tests, stdin); same rules as :func:`read_text`."""
    import tempfile

    with tempfile.NamedTemporaryFile("w", suffix=".txt", delete=False) as fh:
        fh.write(text)
    try:
        return read_text(Path(fh.name), options or ReadOptions()).stream
    finally:
        Path(fh.name).unlink()
