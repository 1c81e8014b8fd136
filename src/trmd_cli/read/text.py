"""Text event files, one event per line.

Accepted layouts (columns default to ``t x y p``; ``columns`` reorders, ``_`` skips one):
- ECD style: ``t x y p`` with t in float seconds;
- E2VID style: a first line ``W H`` (sensor size), then events;
- EVDI style: integer microseconds;
- header lines (non-numeric) and ``#`` comments are skipped; separators are blanks or commas.
Time unit: a t column written with a decimal point or exponent is seconds, integers are µs,
unless ``time_unit`` says otherwise. Polarity 0/−1 = OFF, 1 = ON.

Every event line has as many fields as there are columns: a line with more is refused, not cut
(``columns`` names them all, ``_`` for one to skip). A line whose time is ``nan`` or ``inf`` is
an event line with a time that cannot be true (refused), never a header.

The file is read in blocks of whole lines (:data:`TEXT_BLOCK_BYTES`), each parsed by pandas'
C parser (numpy's when pandas is missing, and to name a malformed line): one pass when it is
opened checks every event and indexes the blocks; files of up to
:data:`~trmd_cli.read.chunked.CACHE_MAX_EVENTS` events stay in memory, longer ones are read
again a block at a time (memory: one window).
"""

from __future__ import annotations

import io
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError, InputError
from ..events import make_stream
from ..units import to_microseconds
from .chunked import Chunk, ChunkedRecording

__all__ = ["read_text", "parse_text_events", "TextRecording", "TEXT_BLOCK_BYTES"]

_NUM = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")
#: a time that cannot be true, but is a number: the line is an event line
_NONFINITE = re.compile(r"^[-+]?(nan|inf|infinity)$", re.IGNORECASE)
#: bytes of whole lines parsed at once (about a million events)
TEXT_BLOCK_BYTES = 32 << 20


def _split(line: str) -> list[str]:
    return [f for f in re.split(r"[,\s;]+", line.strip()) if f]


def _is_numeric(fields: list[str]) -> bool:
    return bool(fields) and any(_NUM.match(f) for f in fields) and all(
        _NUM.match(f) or _NONFINITE.match(f) for f in fields)


class _UnitIsSeconds(Exception):
    """A fractional time turned up in a file whose first time looked like whole µs."""


class TextRecording(ChunkedRecording):
    """A text event file, read in blocks of lines (see the module docstring)."""

    size_guess_note = ("the file stores no sensor size: using max+1 of the coordinates "
                       "(pass `sensor=(W, H)` to set it)")

    def __init__(self, path: Path, options, *, block_bytes: int | None = None) -> None:
        path = Path(path)
        # (a byte-order mark, as some Windows editors write, is not part of the first line)
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            head = [fh.readline() for _ in range(64)]
        skip, sensor, warnings = 0, options.sensor, []
        columns = options.columns or ("t", "x", "y", "p")
        first_data = None
        for i, line in enumerate(head):
            fields = _split(line.split("#", 1)[0])
            if not fields:
                skip = i + 1
                continue
            if not _is_numeric(fields):
                numbers = sum(bool(_NUM.match(f) or _NONFINITE.match(f)) for f in fields)
                if len(fields) == len(columns) and numbers >= len(columns) - 1:
                    # an event line with one bad field, not a header such as "t,x,y,p": its
                    # event must not vanish unsaid
                    raise FormatError(f"malformed event line {i + 1}: '{line.strip()}'",
                                      path=path, hint="fix or remove that line")
                skip = i + 1  # a header such as "t,x,y,p"
                continue
            if len(fields) == 2 and first_data is None and i == skip:
                # E2VID: "W H" on the first line
                if sensor is None:
                    try:
                        w, h = (float(f) for f in fields)
                    except ValueError:
                        w = h = 0.0
                    if not (w.is_integer() and h.is_integer() and 0 < w <= 65535
                            and 0 < h <= 65535):
                        raise FormatError(f"the first line '{' '.join(fields)}' is not a sensor "
                                          "size W H", path=path,
                                          hint="fix that line or pass `sensor=(W, H)`")
                    sensor = (int(w), int(h))
                skip = i + 1
                continue
            first_data = fields
            break
        if first_data is None:
            raise FormatError("no event lines found (truncated, or not an event file?)",
                              path=path, hint="expected lines like '0.000123 45 67 1' (t x y p)")
        if len(first_data) != len(columns):
            more = len(first_data) > len(columns)
            raise FormatError(
                f"event lines have {len(first_data)} columns, expected {len(columns)} "
                f"({' '.join(columns)})" + (": the others would be dropped" if more else ""),
                path=path, hint="use `columns` to say which column is which" + (
                    " (`_` for one to skip), e.g. `columns=t,x,y,p,_`" if more else ""))
        delim = "," if "," in head[skip] else None
        if delim is None and all(("  " not in ln and "\t" not in ln and not ln.startswith(" "))
                                 for ln in head[skip:] if ln.strip()):
            delim = " "  # single spaces: pandas' fast path (a regex separator halves its speed)
        with open(path, "rb") as fh:
            if fh.read(3) != b"\xef\xbb\xbf":
                fh.seek(0)
            for _ in range(skip):
                fh.readline()
            start = fh.tell()
        t_field = first_data[columns.index("t")]
        unit = options.time_unit
        self._unit_fixed = unit is not None or "." in t_field or "e" in t_field.lower()
        if unit is None:
            # the whole column decides: eSL-Net writes the first time as "0" and the rest as
            # fractions of a second, and one integer-looking row must not truncate them all
            unit = "s" if self._unit_fixed else "us"
        size = sensor or options.frame_size  # else the index pass takes max+1 and says so
        w, h = size if size else (None, None)
        super().__init__(path, "text", w, h, warnings)
        self._options, self._columns, self._delim = options, columns, delim
        self._start, self._first_line, self._unit = start, skip + 1, unit
        self._block = int(TEXT_BLOCK_BYTES if block_bytes is None else block_bytes)
        try:
            self._index()
        except _UnitIsSeconds:
            self._unit, self._unit_fixed = "s", True
            self.warnings = list(warnings)
            self.width, self.height = w, h
            self._index()
        self.times_unit = self._unit

    def _index(self) -> None:
        self._changes, self._events, self._indexing = 0, 0, True
        self._last_t: int | None = None
        try:
            self._build_index()
        finally:
            self._indexing = False
        n = self.num_events()
        if n >= 1000 and self._changes + 1 < 16:
            first, last = self.time_range_us()
            self.warnings.append(
                f"{n} events fall on only {self._changes + 1} distinct times ({last - first} µs "
                f"in all, read as {self._unit}): the time unit is probably wrong — set "
                "`time_unit`")

    # -- decoding ---------------------------------------------------------------------------

    def _decode(self, start: int = 0, resume: Any = None) -> Iterator[Chunk]:
        offset, line, first = (self._start, self._first_line, 0) if resume is None else resume
        k = start
        with open(self.path, "rb") as fh:
            fh.seek(offset)
            rest = b""
            while True:
                data = fh.read(self._block)
                buf = rest + data
                if not buf:
                    return
                if data:
                    cut = buf.rfind(b"\n") + 1
                    if cut == 0:  # a line longer than a block: read on
                        rest = buf
                        continue
                else:
                    cut = len(buf)  # the end of the file: its last line, newline or not
                block, rest = buf[:cut], buf[cut:]
                chunk = self._parse(k, block, line, first, (offset, line, first))
                yield chunk
                offset += len(block)
                line += block.count(b"\n")
                first += len(chunk.t)
                k += 1

    def _parse(self, k: int, block: bytes, line: int, first: int, resume) -> Chunk:
        cols = _parse_block(self.path, block, self._delim, self._columns, line)
        t_raw = cols["t"]
        if not self._unit_fixed and self._indexing and len(t_raw):
            with np.errstate(invalid="ignore"):  # a non-finite time is reported below
                if not bool(np.all(np.mod(t_raw, 1.0) == 0.0)):
                    raise _UnitIsSeconds()
        try:
            t = to_microseconds(t_raw, self._unit, first=first)
            x, y = cols["x"], cols["y"]
            if self._options.one_based:
                x, y = x - 1, y - 1
            s = make_stream(x, y, t, cols["p"], self.width, self.height, source=str(self.path),
                            first=first)
        except InputError as e:
            raise InputError(e.detail, path=self.path, hint=e.hint) from None
        if self._indexing and len(s.t):
            self._changes += int(np.count_nonzero(np.diff(s.t)))
            if self._last_t is not None and int(s.t[0]) != self._last_t:
                self._changes += 1
            self._last_t = int(s.t[-1])
        return Chunk(k, s.x, s.y, s.t, s.p, resume=resume)

    def _time_error(self, index: int) -> InputError:
        return InputError(f"event times are not sorted (event {index} goes back in time)",
                          path=self.path, hint="sort the events by time first")

    @property
    def stream(self):
        """All events (for callers that held the whole file before it was streamed)."""
        return self.events()


def _parse_block(path: Path, block: bytes, delim: str | None, columns: tuple[str, ...],
                 line: int) -> dict[str, np.ndarray]:
    """The columns of a block of whole lines whose first is line ``line`` of the file."""
    comments = b"#" in block
    try:
        cols = _fast_parse(block, delim, columns, comments=comments)
        if cols is None:
            text = io.TextIOWrapper(io.BytesIO(block), encoding="utf-8")
            data = np.loadtxt(text, comments="#", delimiter=delim, ndmin=2, dtype=np.float64)
            if data.size and data.shape[1] != len(columns):
                raise ValueError(f"lines have {data.shape[1]} fields, expected {len(columns)} "
                                 "at row 0")
            if not data.size:
                data = np.zeros((0, len(columns)))
            cols = {name: data[:, i] for i, name in enumerate(columns) if name != "_"}
    except ValueError as e:
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        changed = re.search(r"number of columns changed from (\d+) to (\d+) at row (\d+)", msg)
        if changed:  # numpy counts this row from 1
            msg = (f"it has {changed[2]} fields, the lines before it {changed[1]} "
                   f"(at row {int(changed[3]) - 1})")
        m = re.search(r"\b(line|row) (\d+)", msg)
        # numpy counts rows from 0 and lines from 1, within the block
        where = "" if not m else \
            f" near line {int(m[2]) + (line if m[1] == 'row' else line - 1)}"
        msg = re.sub(r" \(at row \d+\)$", "", msg)
        raise FormatError(f"malformed event line{where}: {msg[:160]}", path=path,
                          hint="every line needs numbers t x y p; a short last line means the "
                               "copy is incomplete (copy it again, or delete that line)") from None
    return cols


def _fast_parse(block: bytes, delim: str | None, columns: tuple[str, ...], *,
                comments: bool = True) -> dict[str, np.ndarray] | None:
    """pandas' C parser when installed (2–3× numpy's, more with integer columns typed as
    such); None to fall back to numpy, which also names a malformed line better.

    ``comment`` costs pandas ~50 %, so it is passed only when the block holds a ``#``. A line
    with another number of fields fails here, and numpy says which."""
    try:
        import pandas as pd
    except ImportError:
        return None
    use = [i for i, name in enumerate(columns) if name != "_"]
    typed = {i: (np.float64 if columns[i] == "t" else np.int64) for i in use}
    for dtype in (typed, np.float64):  # coordinates written as "12.0" need the second pass
        try:
            extra = {"comment": "#"} if comments else {}
            frame = pd.read_csv(io.BytesIO(block), sep=r"\s+" if delim is None else delim,
                                header=None, dtype=dtype, engine="c", skip_blank_lines=True,
                                **extra)
        except Exception:  # noqa: BLE001 - try the next dtype, then numpy
            continue
        if frame.shape[1] != len(columns):
            return None
        cols = {columns[i]: frame[i].to_numpy() for i in use}
        if any(c.dtype.kind == "f" and np.isnan(c).any() for c in cols.values()):
            return None  # a short line: let numpy report it
        return cols
    return None


def read_text(path: Path, options) -> TextRecording:
    """Open a text event file (checked and indexed in one pass; see the module docstring)."""
    return TextRecording(Path(path), options)


def parse_text_events(text: str, options=None):
    """Parse events from a string (tests, stdin); same rules as :func:`read_text`."""
    import tempfile

    from .base import ReadOptions

    with tempfile.NamedTemporaryFile("w", suffix=".txt", delete=False) as fh:
        fh.write(text)
    try:
        with read_text(Path(fh.name), options or ReadOptions()) as rec:
            return rec.events()
    finally:
        Path(fh.name).unlink()
