"""The RPG event-camera layout (the Event Camera Dataset and the sets made like it): a folder.

::

    seq/
      events.txt     one event per line: t x y p — t in seconds (decimal), x column, y row,
                     p 1 = ON, 0 = OFF
      images.txt     one frame per line: t path — t in seconds, path relative to seq/
      images/        the frames (PNG …), read as float32 [0, 1]
      imu.txt, groundtruth.txt, calib.txt …   not read

Units and conventions:

* time: the decimal seconds are read digit by digit (never through a float) and kept as whole
  microseconds; digits finer than a microsecond are dropped (floor), which moves every time by
  the same amount when they share one sub-µs remainder, as recordings of one camera do — else a
  warning says intervals may differ by < 1 µs (:mod:`trmd_cli.read.stamps`);
* x = column, y = row, (0, 0) at the top-left;
* sensor size: ``sensor``, else the first frame's size, else max+1 (warned);
* frames carry one time stamp each: their exposure window comes from ``exposure_length_us`` and
  ``stamp`` (see :func:`~trmd_cli.read.stamps.stamped_exposures`); without
  ``exposure_length_us`` the frames are listed but cannot be deblurred.

``events.txt`` is read in pieces of :data:`RPG_CHUNK_BYTES`: opening it parses the file once,
keeping a small index (byte offset, first and last time of every piece); windows are then read
by seeking to the pieces that hold them (:class:`~trmd_cli.read.chunked.ChunkedRecording`).
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError, InputError
from ..events import Exposure
from .base import Frame, ReadOptions
from .chunked import Chunk, ChunkedRecording
from .stamps import EXPOSURE_HINT, SubMicrosecond, stamped_exposures

__all__ = ["read_rpg", "RpgRecording", "parse_event_lines", "RPG_CHUNK_BYTES"]

#: bytes of events.txt parsed per piece (~70 000 lines)
RPG_CHUNK_BYTES = 2 << 20

_DIGIT = np.zeros(256, bool)
_DIGIT[ord("0"):ord("9") + 1] = True
_SEP = np.zeros(256, bool)
_SEP[[ord(" "), ord("\t"), ord(","), ord("\r"), ord("\n")]] = True
_POW10 = np.array([10 ** k for k in range(19)], np.int64)
#: byte → its digit's value (0 for anything else); bytes that may appear in events.txt
_VALUE = np.zeros(256, np.uint8)
_VALUE[ord("0"):ord("9") + 1] = np.arange(10)
_ALLOWED = _DIGIT | _SEP
_ALLOWED[ord(".")] = True

_HINT = ("each line of events.txt is 't x y p': seconds (e.g. 1468941032.229165635), column, "
         "row and polarity 0/1")


def parse_event_lines(buf: bytes, first_line: int = 1, path=None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Parse whole lines ``t x y p`` (t in decimal seconds) exactly, with numpy.

    Args:
        buf: complete lines (the last one may lack its newline).
        first_line: the file's line number of the first line, for messages.

    Returns:
        (t_us, x, y, p, sub_ns): int64 µs (floored), uint16, uint16, int8 ±1, and the dropped
        sub-µs part of each time in ns (digits past the 9th are cut).
    Raises:
        FormatError: a line that is not four numbers of that form, naming it.
    """
    a = np.frombuffer(buf, np.uint8)
    if len(a) == 0:
        e = np.zeros(0, np.int64)
        return e, e.astype(np.uint16), e.astype(np.uint16), e.astype(np.int8), e
    newlines = np.flatnonzero(a == ord("\n"))
    allowed = _ALLOWED[a]
    if not allowed.all():
        at = int(np.argmin(allowed))
        _fail(buf, int(np.searchsorted(newlines, at)), first_line, path)
    sep = _SEP[a]
    dot = a == ord(".")
    tok = ~sep
    starts = np.flatnonzero(tok & np.concatenate([[True], sep[:-1]]))
    ends = np.flatnonzero(tok & np.concatenate([sep[1:], [True]])) + 1
    line_of = np.searchsorted(newlines, starts)  # the line of each token
    # every line that holds anything holds four tokens
    change = np.flatnonzero(np.diff(line_of)) + 1
    first_tok = np.concatenate([[0], change])
    counts = np.diff(np.concatenate([first_tok, [len(starts)]]))
    if len(counts) and (counts != 4).any():
        _fail(buf, int(line_of[first_tok[np.argmax(counts != 4)]]), first_line, path)
    n = len(starts) // 4
    starts4, ends4 = starts.reshape(n, 4), ends.reshape(n, 4)
    lens = ends4 - starts4
    # dots: one at most, and only in the time
    dots = np.flatnonzero(dot)
    tok_of_dot = np.searchsorted(starts, dots, side="right") - 1
    if len(dots) and ((tok_of_dot % 4 != 0).any() or (np.diff(tok_of_dot) == 0).any()):
        k = int(tok_of_dot[(tok_of_dot % 4 != 0).argmax()] if (tok_of_dot % 4 != 0).any()
                else tok_of_dot[np.flatnonzero(np.diff(tok_of_dot) == 0)[0]])
        _fail(buf, int(line_of[k]), first_line, path)
    dot_at = np.full(n, -1, np.int64)
    dot_at[tok_of_dot // 4] = dots
    has_dot = dot_at >= 0
    t_start, t_end = starts4[:, 0], ends4[:, 0]
    int_end = np.where(has_dot, dot_at, t_end)
    frac_len = np.where(has_dot, t_end - dot_at - 1, 0)
    if (int_end - t_start > 12).any() or (lens[:, 1:] > 5).any() or (int_end == t_start).any():
        row = int(np.argmax((int_end - t_start > 12) | (lens[:, 1:] > 5).any(1)
                            | (int_end == t_start)))
        _fail(buf, int(line_of[4 * row]), first_line, path)
    digits = _VALUE[a]
    seconds = _numbers(digits, t_start, int_end, 12)
    keep = np.minimum(frac_len, 6)
    micro = _numbers(digits, dot_at + 1, dot_at + 1 + keep, 6) * _POW10[6 - keep]
    ns_len = np.clip(frac_len - 6, 0, 3)
    sub_ns = _numbers(digits, dot_at + 7, dot_at + 7 + ns_len, 3) * _POW10[3 - ns_len]
    sub_ns[~has_dot] = 0
    micro[~has_dot] = 0
    t_us = seconds * 1_000_000 + micro
    x = _numbers(digits, starts4[:, 1], ends4[:, 1], 5)
    y = _numbers(digits, starts4[:, 2], ends4[:, 2], 5)
    pol = _numbers(digits, starts4[:, 3], ends4[:, 3], 5)
    if len(pol) and ((pol > 1).any() or (x > 65535).any() or (y > 65535).any()):
        row = int(np.argmax((pol > 1) | (x > 65535) | (y > 65535)))
        _fail(buf, int(line_of[4 * row]), first_line, path)
    return (t_us, x.astype(np.uint16), y.astype(np.uint16),
            np.where(pol == 1, 1, -1).astype(np.int8), sub_ns)


def _numbers(digits: np.ndarray, start: np.ndarray, end: np.ndarray, width: int
             ) -> np.ndarray:
    """The whole number written by ``digits[start:end]`` per row (0 where empty), int64.

    Every number is gathered right-aligned into a row of ``width`` digits (the longest it may
    be; the caller checks) and weighted by the powers of ten: no Python loop. The product runs
    in float64, exact for the <= 12 digits asked of it (every partial sum is below 2**53)."""
    idx = end[:, None] - width + np.arange(width)
    d = np.where(idx >= start[:, None], digits[np.clip(idx, 0, None)], 0).astype(np.float64)
    return (d @ _POW10[width - 1::-1].astype(np.float64)).astype(np.int64)


def _fail(buf: bytes, line: int, first_line: int, path) -> None:
    lines = buf.split(b"\n")
    text = lines[line].decode("utf-8", "replace").strip() if line < len(lines) else ""
    raise FormatError(f"line {first_line + line} of events.txt, {text[:60]!r}, is not 't x y p'",
                      path=path, hint=_HINT)


def _read_images_txt(path: Path) -> list[tuple[int, int, Path]]:
    """images.txt → (stamp µs, dropped sub-µs ns, image path) per frame, in file order."""
    out: list[tuple[int, int, Path]] = []
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise InputError(f"cannot read the frame list ({e.strerror})", path=path) from None
    for n, line in enumerate(text.splitlines(), 1):
        body = line.split("#", 1)[0].strip()
        if not body:
            continue
        parts = body.split(None, 1)
        m = re.fullmatch(r"(\d+)(?:\.(\d*))?", parts[0])
        if not m or len(parts) < 2:
            raise FormatError(f"line {n}, {body[:60]!r}, is not 't path'", path=path,
                              hint="each line of images.txt is a time in seconds and an image "
                                   "path, e.g. '1.25 images/frame_00000001.png'")
        frac = (m[2] or "")
        us = int(m[1]) * 1_000_000 + int((frac[:6] or "0").ljust(6, "0"))
        sub = int((frac[6:9] or "0").ljust(3, "0"))
        out.append((us, sub, path.parent / parts[1].strip()))
    return out


class RpgRecording(ChunkedRecording):
    """An RPG-layout folder: events from events.txt (chunked by bytes), frames from
    images.txt."""

    def __init__(self, folder: Path, options: ReadOptions) -> None:
        self.folder = Path(folder)
        self._events_path = self.folder / "events.txt"
        warnings: list[str] = []
        if options.time_unit not in (None, "s"):
            warnings.append(f"`time_unit={options.time_unit!r}` ignored: the RPG layout "
                            "writes seconds")
        if options.columns is not None or options.one_based:
            warnings.append("`columns` and `one_based` ignored: the RPG layout is 't x y p' "
                            "with 0-based pixels")
        self._sub = SubMicrosecond()
        listed = _read_images_txt(self.folder / "images.txt")
        for k, (_, _, img) in enumerate(listed):
            if not img.is_file():
                raise InputError(f"images.txt line {k + 1} names {img.name}, which does not "
                                 "exist", path=img.parent, hint="copy the frames folder too")
        self._images = [p for _, _, p in listed]
        stamps = [us for us, _, _ in listed]
        self._sub.add(np.array([us * 1000 + sub for us, sub, _ in listed], np.int64))
        size = options.sensor
        if size is None and self._images:
            from .frames import read_image

            h, w = read_image(self._images[0]).shape[:2]
            size = (int(w), int(h))
        width, height = (None, None) if size is None else size
        super().__init__(self.folder, "rpg", width, height, warnings)
        self._size = os.path.getsize(self._events_path)
        self._build_index()
        windows, notes = stamped_exposures(stamps, None, options.exposure_length_us,
                                           options.stamp, stored="images.txt")
        self._windows = windows
        self.warnings.extend(notes)
        note = self._sub.note()
        if note:
            self.warnings.append(note)
        #: how to give exposure times, for messages about frames without them
        self.exposure_hint = EXPOSURE_HINT

    def _decode(self, start: int = 0, resume: Any = None) -> Iterator[Chunk]:
        """Pieces of events.txt: each is the whole lines within :data:`RPG_CHUNK_BYTES` from
        where the previous one ended, so a piece is the same whichever piece decoding starts
        at (``resume`` = its byte offset and first line number)."""
        pos, line = (0, 1) if resume is None else resume
        k = 0 if resume is None else start
        with open(self._events_path, "rb") as fh:
            while pos < self._size:
                fh.seek(pos)
                data = fh.read(RPG_CHUNK_BYTES)
                if not data:
                    return
                if pos + len(data) < self._size:
                    cut = data.rfind(b"\n") + 1
                    if cut == 0:
                        raise FormatError(f"line {line} of events.txt is longer than "
                                          f"{RPG_CHUNK_BYTES} bytes: not an event line",
                                          path=self._events_path, hint=_HINT)
                    data = data[:cut]
                if resume is not None or k >= start:
                    t, x, y, p, sub = parse_event_lines(data, line, self._events_path)
                    self._sub.add(t * 1000 + sub)
                    yield Chunk(k, x, y, t, p, (pos, line))
                pos += len(data)
                line += data.count(b"\n")
                k += 1

    def frames(self) -> Iterator[Frame]:
        """The frames of images.txt in order, one read at a time."""
        from .frames import read_image

        for i, (path, window) in enumerate(zip(self._images, self._windows, strict=True)):
            yield Frame(read_image(path), window, i, path.stem)

    def frame_exposures(self) -> list[Exposure]:
        return [w for w in self._windows if w is not None]

    def num_frames(self) -> int:
        return len(self._images)


def read_rpg(path: Path, options: ReadOptions) -> RpgRecording:
    """Open an RPG-layout folder (events.txt, images.txt, images/)."""
    path = Path(path)
    if not path.is_dir():
        raise InputError("the RPG layout is a folder", path=path,
                         hint="give the folder that holds events.txt and images.txt")
    return RpgRecording(path, options)
