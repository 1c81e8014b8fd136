"""Prophesee recordings: EVT 2.0 ``.raw``, EVT 3.0 ``.raw`` and ``.dat`` (CD events).

Units and conventions (all three formats):

* time: microseconds on the camera's clock, kept as they are (a Metavision recording usually
  starts some seconds after the camera did; nothing is subtracted);
* x = column, y = row, (0, 0) at the top-left; polarity 1 = ON (+1), 0 = OFF (-1);
* sensor size from the header (``% geometry 1280x720``, ``% format EVT3;height=720;width=1280``,
  or ``% Width``/``% Height`` in .dat); else from the sensor named by ``% plugin_name`` (Gen3 →
  640x480, Gen4/IMX636 → 1280x720, GenX320 → 320x320); else ``sensor``; else max+1 (warned).

Prophesee cameras record no intensity frames. Deblurring their events needs frames from a second
camera whose clock is aligned with the event camera's (hardware trigger or a measured offset):
give the frames as a folder with ``Exposure_start.txt``/``Exposure_end.txt``, or one window with
``exposure`` (see :mod:`trmd_cli.read.folders`).

Decoders:

* EVT 2.0 — decoded here with numpy (32-bit words: type in bits 31–28; CD_OFF 0x0 / CD_ON 0x1
  carry the 6 low time bits, x (11 bits) and y (11 bits); EVT_TIME_HIGH 0x8 carries time bits
  33–6; EXT_TRIGGER 0xA, OTHERS 0xE and CONTINUED 0xF are skipped). Chunks can be decoded in any
  order, so windows of a large file are read without decoding the rest.
* .dat — decoded here with numpy (after the ``%`` header, one byte event type, one byte event
  size = 8, then records of uint32 time µs and uint32 with x in bits 0–13, y in bits 14–27,
  polarity in bits 28–31). The 32-bit time wraps after 71.6 min and is unwrapped. Files larger
  than the in-memory cache are indexed on their raw records (times, polarities, coordinates
  checked, not decoded), and the chunks with nothing to repair are later unpacked without the
  repairs' checks: one decoding per read, as for files in the cache.
* EVT 3.0 — decoded with the ``evt3`` package (not expelliarmus: it doubles EVT 3.0 times).
  Small files are decoded when opened. Larger ones open on a scan of their raw words, which
  finds the points where a fresh decoder can start (a TIME_HIGH word, with the clock's wraps,
  the row and the vector column there): they are decoded once, when read, and windows far into
  the file are reached without decoding what comes before. The scan runs beside the first read:
  a read of the whole file decodes meanwhile.

Both numpy decoders agree event for event with expelliarmus on the shared recordings (tests).
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError
from ..events import EventStream
from ..threads import beside
from .base import ReadOptions
from .chunked import IN_ORDER_HINT, Chunk, ChunkedRecording, ChunkSummary, time_slice
from .evt3_words import Evt3Scan, resume_prefix, scan_evt3

__all__ = [
    "read_evt2",
    "read_evt3",
    "read_dat",
    "PropheseeHeader",
    "parse_header",
    "decode_evt2_words",
    "decode_dat_records",
    "EVT2_CHUNK_WORDS",
    "DAT_CHUNK_EVENTS",
]

#: 32-bit words per EVT 2.0 chunk (4 MiB)
EVT2_CHUNK_WORDS = 1 << 20
#: records per .dat chunk (8 MiB)
DAT_CHUNK_EVENTS = 1 << 20
#: bytes of EVT 3.0 fed to the evt3 decoder per chunk (files decoded when opened)
EVT3_CHUNK_BYTES = 4 << 20
#: EVT 3.0 bodies up to this many bytes are decoded when opened; larger ones open on a scan
#: of their words (a fifth of a decoding) and are decoded once, as they are read
EVT3_EAGER_BYTES = 32 << 20

#: sensor sizes by the name fragments found in ``% plugin_name`` / ``% sensor_generation``
_KNOWN_SENSORS = (("genx320", (320, 320)), ("imx636", (1280, 720)), ("gen41", (1280, 720)),
                  ("gen4", (1280, 720)), ("gen31", (640, 480)), ("gen3", (640, 480)))

_EVT2_TYPES = (0x0, 0x1, 0x8, 0xA, 0xE, 0xF)
_EVT2_VALID = np.zeros(16, bool)
_EVT2_VALID[list(_EVT2_TYPES)] = True


#: hint for files that cannot be decoded
_DAMAGED = "the file may be incomplete or damaged: copy it again or re-export the recording"
#: EVT 2.0 words read past a chunk's end to find the time words that follow it
_LOOKAHEAD_WORDS = 1 << 14


@dataclass(frozen=True)
class PropheseeHeader:
    """The ``%`` header of a .raw/.dat file.

    Attributes:
        fields: lower-cased first word of each line → the rest of the line.
        data_offset: byte offset where binary data starts.
        width, height: sensor size if the header states it, else None.
        encoding: ``"evt2"``, ``"evt21"``, ``"evt3"`` or None when the header does not say.
        sensor_hint: sensor size inferred from the plugin / sensor generation name, or None.
        size_line: the header line(s) the size was read from, as written (for messages).
    """

    fields: dict[str, str] = field(default_factory=dict)
    data_offset: int = 0
    width: int | None = None
    height: int | None = None
    encoding: str | None = None
    sensor_hint: tuple[int, int] | None = None
    size_line: str | None = None


def parse_header(head: bytes) -> PropheseeHeader:
    """Parse the ``%`` lines at the start of ``head`` (the first bytes of the file).

    A line counts as header only if it is printable text ending in a newline: binary data that
    happens to start with ``%`` (0x25) is not swallowed. ``% end`` closes the header.
    """
    fields: dict[str, str] = {}
    pos = 0
    while head.startswith(b"%", pos):
        nl = head.find(b"\n", pos, pos + 4096)
        if nl < 0:
            break
        line = head[pos:nl].rstrip(b"\r")
        if any(c < 0x20 and c != 0x09 for c in line) or b"\x7f" in line:
            break
        text = line[1:].decode("latin-1").strip()
        pos = nl + 1
        if text.lower() == "end":
            break
        key, _, value = text.partition(" ")
        if key:
            fields[key.lower()] = value.strip()
    width = height = None
    encoding = None
    size_line = None
    if "geometry" in fields:
        m = re.match(r"\s*(\d+)\s*x\s*(\d+)", fields["geometry"])
        if m:
            width, height = int(m[1]), int(m[2])
            size_line = f"% geometry {fields['geometry']}"
    if "format" in fields:
        parts = fields["format"].split(";")
        name = parts[0].strip().lower()
        if re.fullmatch(r"evt\d+", name):
            encoding = name
        opts = dict(p.split("=", 1) for p in parts[1:] if "=" in p)
        if "width" in opts and "height" in opts:
            try:
                width, height = int(opts["width"]), int(opts["height"])
                size_line = f"% format {fields['format']}"
            except ValueError:
                pass
    if width is None and "width" in fields and "height" in fields:
        try:
            width, height = int(fields["width"]), int(fields["height"])
            size_line = f"% Width {fields['width']} / % Height {fields['height']}"
        except ValueError:
            pass
    if encoding is None and "evt" in fields:
        encoding = {"3.0": "evt3", "2.0": "evt2", "2.1": "evt21"}.get(fields["evt"].strip())
    hint = None
    name = (fields.get("plugin_name", "") + " " + fields.get("sensor_generation", "")).lower()
    for fragment, size in _KNOWN_SENSORS:
        if fragment in name.replace(".", ""):
            hint = size
            break
    return PropheseeHeader(fields, pos, width, height, encoding, hint, size_line)


def _read_header(path: Path) -> PropheseeHeader:
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    header = parse_header(head)
    rest = head[header.data_offset:]
    if rest.startswith(b"%") and len(head) < 1 << 16 and b"\n" not in rest[:4096] and \
            all(c >= 0x20 or c == 0x09 for c in rest):
        # the whole file was read, and it ends in a "%" line that never ends: cut inside its
        # header (what follows is no event data to keep)
        raise FormatError("the file ends inside its header (truncated?)", path=path,
                          hint=_DAMAGED)
    return header


#: no event camera made has a side longer than this (the largest are 1280x720; EVT 2.0 and 3.0
#: address 2048x2048): a header declaring more is damaged, and would make every image of the
#: run that large
MAX_SENSOR_SIDE = 8192


def _sensor(header: PropheseeHeader, options: ReadOptions,
            warnings: list[str], path: Path | None = None) -> tuple[int | None, int | None]:
    if header.width is not None and header.height is not None and not (
            0 < header.width <= MAX_SENSOR_SIDE and 0 < header.height <= MAX_SENSOR_SIDE):
        said = f"the header line '{header.size_line}' declares a {header.width}x{header.height} " \
               f"sensor"
        if options.sensor:
            warnings.append(f"{said}, which no camera has: using `sensor={options.sensor}`")
            return options.sensor
        raise FormatError(f"{said}; no event camera is larger than {MAX_SENSOR_SIDE}x"
                          f"{MAX_SENSOR_SIDE} (a damaged header?)", path=path,
                          hint="repair that line, or pass `sensor=(W, H)` with the camera's size")
    if header.width and header.height:
        if options.sensor and tuple(options.sensor) != (header.width, header.height):
            warnings.append(f"`sensor={options.sensor}` ignored: the "
                            f"file says {header.width}x{header.height}")
        return header.width, header.height
    if options.sensor:
        return options.sensor
    if options.frame_size:
        return options.frame_size
    if header.sensor_hint:
        w, h = header.sensor_hint
        warnings.append(f"the header states no sensor size; using {w}x{h} for the "
                        f"{header.fields.get('plugin_name', 'named sensor')} (pass "
                        "`sensor=(W, H)` to override)")
        return w, h
    return None, None


def _ignore_time_unit(options: ReadOptions, fmt: str, warnings: list[str]) -> None:
    if options.time_unit not in (None, "us"):
        warnings.append(f"`time_unit={options.time_unit!r}` ignored: {fmt} times are "
                        "microseconds by specification")


def _whole_records(path: Path, offset: int, size: int, what: str) -> int:
    """Number of whole records after ``offset``; a partial last record means truncation."""
    total = os.path.getsize(path)
    if total < offset:
        raise FormatError("the file ends inside its header (truncated?)", path=path,
                          hint=_DAMAGED)
    n, rest = divmod(total - offset, size)
    if rest:
        raise FormatError(
            f"the file ends with {rest} byte(s) of a partial {what} (truncated?)", path=path,
            hint=f"if the recording was interrupted, keep its complete part: "
                 f"truncate -s {total - rest} FILE (on a copy)")
    return n


# -- corrupt time words --------------------------------------------------------------------

#: a step of the clock by more than this (µs) between consecutive time words is more than a
#: recording holds between two of them: if the clock comes back within the next
#: :data:`RETURN_WORDS` time words, the words away from it are corrupt, not a wrap or a gap
CLOCK_JUMP_US = 1 << 26  # 67 s
RETURN_WORDS = 8


def _steps(to: np.ndarray, start, period: int) -> np.ndarray:
    """Clock steps ``start → to`` as the unwrapping reads them: a step back by more than half
    the counter's period is the counter wrapping (so a step lies in [-period/2, period))."""
    d = np.asarray(to, np.int64) - np.asarray(start, np.int64)
    return np.where(d < -(period >> 1), d + period, d)


def _big_steps(raw: np.ndarray, before: int, period: int, jump: int) -> np.ndarray:
    """Indices ``i`` where the step ``raw[i-1] → raw[i]`` (``before → raw[0]`` for i = 0), read
    as the unwrapping reads it (:func:`_steps`), is larger than ``jump`` either way.

    Unwrapping only changes steps back by more than half the period, which ``jump`` (far below
    it) already calls large: so the raw difference picks the candidates in two passes over the
    chunk, and only those few are unwrapped.
    """
    d = np.empty(len(raw), np.int64)
    d[0] = int(raw[0]) - int(before)
    np.subtract(raw[1:], raw[:-1], out=d[1:])
    cand = np.flatnonzero(np.abs(d) > jump)
    if len(cand) == 0:
        return cand
    return cand[np.abs(_steps(d[cand], 0, period)) > jump]


def clock_excursions(raw: np.ndarray, last: int, period: int, jump: int,
                     ahead: np.ndarray | None = None, at_end: bool = True) -> np.ndarray:
    """Which time words of ``raw`` are corrupt: bool mask.

    A word is corrupt when the clock (``raw``, a counter wrapping at ``period``) steps away from
    the last good word by more than ``jump``, forward or back, and comes back — a step of 0 to
    ``jump`` forward from that good word — within :data:`RETURN_WORDS` words; or, having jumped
    forward by more than half the counter's period, when the file ends first. A step that
    stays (a long quiet gap, a step back that is an error of its own) is kept: the words after
    it are judged from it.

    Args:
        raw: the time words of a chunk, in file order (int64). last: the last good word before
            them (-1 at the start of the file). ahead: the time words after the chunk (at most
            :data:`RETURN_WORDS`), to see a return across the chunk's end. at_end: no more
            time words follow ``ahead``.
    """
    n = len(raw)
    bad = np.zeros(n, bool)
    if n == 0:
        return bad
    if last >= 0:
        suspects = _big_steps(raw, last, period, jump)
        if len(suspects) == 0:  # the usual chunk: no copy of it is needed
            return bad
    ext = raw if ahead is None or not len(ahead) else np.concatenate([raw, ahead])
    if last < 0 and len(ext) > 2:
        # the file's first time word has nothing before it to be judged by: it is corrupt when
        # far from all the words after it, which agree with each other
        follow = ext[1:1 + RETURN_WORDS]
        far = np.abs(_steps(follow, ext[0], period)) > jump
        agree = (np.abs(_steps(follow[1:], follow[:-1], period)) <= jump).all()
        if far.all() and agree:
            bad[0] = True
            if n > 1:
                bad[1:] = clock_excursions(raw[1:], int(raw[1]), period, jump, ahead, at_end)
            return bad
    if last < 0:
        suspects = _big_steps(raw, raw[0], period, jump)
    k = 0
    while k < len(suspects):
        i = int(suspects[k])
        if i > 0 and bad[i - 1]:
            k += 1  # judged with the run before it
            continue
        ref = int(raw[i - 1]) if i > 0 else last
        step = int(_steps(raw[i], ref, period))
        if abs(step) <= jump:
            k += 1
            continue
        after = _steps(ext[i + 1:i + 1 + RETURN_WORDS], ref, period)
        back = np.flatnonzero((after >= 0) & (after <= jump))
        if len(back):
            stop = i + 1 + int(back[0])  # the first word back on the clock
        elif step > period >> 1 and at_end and len(after) < RETURN_WORDS and (np.abs(_steps(
                ext[i + 1:], ext[i:-1], period)) <= jump).all():
            # ahead by more than half the counter (a step back, read as ahead), staying there
            # until the file ends: nothing confirms it
            stop = len(ext)
        else:
            k += 1  # the clock stays where it went: a gap, or an error of its own
            continue
        bad[i:min(stop, n)] = True
        k = int(np.searchsorted(suspects, stop, side="left"))
    return bad


def _excursion_note(kind: str, first: int, count: int, to_us: int, from_us: int,
                    dropped: int, what: str) -> str:
    """The warning for corrupt time words skipped while reading."""
    many = f"{count} corrupt {kind}s (the first, {what} {first}," if count > 1 else \
        f"{what} {first} is a corrupt {kind} ("
    events = f"; {dropped} event(s) they timed were dropped" if dropped else ""
    return (f"{many} jumps the clock from {from_us / 1e6:.6f} s to {to_us / 1e6:.6f} s, and "
            f"the next time words jump back): skipped, not taken for a clock wrap{events}")


# -- EVT 2.0 ---------------------------------------------------------------------------------


def decode_evt2_words(words: np.ndarray, state: tuple[int, int, int] = (-1, 0, -1),
                      *, path: Path | None = None, first_word: int = 0,
                      ahead: np.ndarray | None = None, at_end: bool = True,
                      corrupt: list | None = None):
    """Decode EVT 2.0 words (uint32) into CD events.

    Args:
        words: (W,) uint32 little-endian words.
        state: ``(last_raw_time_high, wraps, time_high)`` carried from the previous chunk;
            ``time_high`` is the unwrapped time-high (units of 64 µs), -1 before the first one
            (-2 after a corrupt one).
        first_word: index of ``words[0]`` in the file, for error messages.
        ahead: the words after ``words`` (a few thousand suffice), to tell a corrupt time-high
            word near the chunk's end; at_end: nothing follows ``ahead``.
        corrupt: if given, one ``(word index, time µs, previous time µs, events dropped)`` is
            appended per corrupt time-high word skipped (see :func:`clock_excursions`).
    Returns:
        ``(x, y, t, p, state_after, dropped)``: uint16, uint16, int64 µs, int8 ±1 arrays, the
        state for the next chunk, and the number of CD events dropped because no time-high word
        preceded them.
    Raises:
        FormatError: a word of a type EVT 2.0 does not define.
    """
    w = np.asarray(words, np.uint32)
    typ = (w >> 28).astype(np.uint8)
    bad = ~_EVT2_VALID[typ]
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise FormatError(f"word {first_word + i} has type 0x{typ[i]:X}, which EVT 2.0 does "
                          "not define (corrupt file, or not EVT 2.0?)", path=path,
                          hint=_DAMAGED)
    last_raw, wraps, time_high = state
    is_th = typ == 0x8
    th_raw = (w[is_th] & 0x0FFFFFFF).astype(np.int64)
    if len(th_raw):
        later = None
        if ahead is not None and len(ahead):
            a = np.asarray(ahead, np.uint32)
            later = (a[(a >> 28) == 0x8] & 0x0FFFFFFF).astype(np.int64)[:RETURN_WORDS]
        skip = clock_excursions(th_raw, last_raw, 1 << 28, CLOCK_JUMP_US >> 6, later, at_end)
        good = ~skip
        kept = th_raw[good]
        th = np.full(len(th_raw), -2, np.int64)  # -2: timed by a corrupt word
        if len(kept):
            prev = np.concatenate([[last_raw if last_raw >= 0 else kept[0]], kept])
            # the 28-bit time-high wraps every 4.77 h: count the big backward steps
            wrap = wraps + np.cumsum(np.diff(prev) < -(1 << 27))
            th[good] = kept + (wrap << 28)
            state_after = (int(kept[-1]), int(wrap[-1]), int(th[-1]))
        else:
            state_after = (last_raw, wraps, -2)
    else:
        th = th_raw
        skip = None
        state_after = state
    is_cd = typ <= 0x1
    # for each CD word, the number of time-high words before it indexes [time_high, *th]
    which = np.cumsum(is_th, dtype=np.int32 if len(w) < 2**31 else np.int64)[is_cd]
    highs = np.concatenate([[time_high], th])[which]
    cd = w[is_cd]
    keep = highs >= 0
    dropped = int((highs == -1).sum())
    if skip is not None and skip.any() and corrupt is not None:
        th_at = np.flatnonzero(is_th)
        lost = np.bincount(which[highs == -2], minlength=len(th) + 1)[1:]
        good_before = np.concatenate([[time_high], th])
        for j in np.flatnonzero(skip & ~np.concatenate([[False], skip[:-1]])):
            run = j + int(np.argmin(skip[j:])) if not skip[j:].all() else len(skip)
            prev_us = int(good_before[j]) << 6 if good_before[j] >= 0 else 0
            corrupt.append((first_word + int(th_at[j]), int(th_raw[j]) << 6, prev_us,
                            int(lost[j:run].sum()), run - j))
    if not keep.all():
        cd, highs = cd[keep], highs[keep]
    t = highs << 6
    t |= (cd >> 22) & 0x3F
    x = ((cd >> 11) & 0x7FF).astype(np.uint16)
    y = (cd & 0x7FF).astype(np.uint16)
    p = (cd >> 28).astype(np.int8)
    p *= 2
    p -= 1
    return x, y, t, p, state_after, dropped


class Evt2Recording(ChunkedRecording):
    """An EVT 2.0 .raw file, decoded in chunks of :data:`EVT2_CHUNK_WORDS` words."""

    def __init__(self, path: Path, options: ReadOptions, chunk_words: int = EVT2_CHUNK_WORDS):
        header = _read_header(path)
        if header.encoding not in (None, "evt2"):
            raise FormatError(f"the header says {header.encoding}, not EVT 2.0", path=path,
                              hint="check the '% evt' / '% format' header lines")
        warnings: list[str] = []
        _ignore_time_unit(options, "EVT 2.0", warnings)
        width, height = _sensor(header, options, warnings, path)
        super().__init__(path, "evt2", width, height, warnings)
        self.header = header
        self._chunk_words = int(chunk_words)
        self._num_words = _whole_records(path, header.data_offset, 4, "32-bit word")
        self._dropped = 0
        self._corrupt: list[tuple[int, int, int, int, int]] = []
        self._counting = True
        self._build_index()
        self._counting = False
        if self._dropped:
            self.warnings.append(f"{self._dropped} event(s) before the first time-high word "
                                 "were dropped (their time is unknown)")
        if self._corrupt:
            word, to_us, from_us, _, _ = self._corrupt[0]
            self.warnings.append(_excursion_note(
                "TIME_HIGH word", word, sum(c[4] for c in self._corrupt), to_us, from_us,
                sum(c[3] for c in self._corrupt), "word"))

    def _decode(self, start: int = 0, resume: Any = None) -> Iterator[Chunk]:
        state = (-1, 0, -1) if resume is None else resume
        k = start
        with open(self.path, "rb") as fh:
            fh.seek(self.header.data_offset + 4 * k * self._chunk_words)
            while k * self._chunk_words < self._num_words:
                words = np.fromfile(fh, "<u4", self._chunk_words)
                here = fh.tell()
                ahead = np.fromfile(fh, "<u4", _LOOKAHEAD_WORDS)
                fh.seek(here)
                end = (k + 1) * self._chunk_words + len(ahead) >= self._num_words
                x, y, t, p, after, dropped = decode_evt2_words(
                    words, state, path=self.path, first_word=k * self._chunk_words,
                    ahead=ahead, at_end=end, corrupt=self._corrupt if self._counting else None)
                if self._counting:
                    self._dropped += dropped
                yield Chunk(k, x, y, t, p, resume=state)
                state = after
                k += 1


def read_evt2(path: Path, options: ReadOptions) -> Evt2Recording:
    """Open a Prophesee EVT 2.0 .raw file (events indexed on open, decoded per window)."""
    return Evt2Recording(Path(path), options)


# -- .dat ------------------------------------------------------------------------------------

_DAT_DTYPE = np.dtype([("t", "<u4"), ("d", "<u4")])


def decode_dat_records(records: np.ndarray, state: tuple[int, int] = (-1, 0), *,
                       path: Path | None = None, first_record: int = 0,
                       ahead: np.ndarray | None = None, at_end: bool = True,
                       corrupt: list | None = None):
    """Decode .dat CD records (structured ``t``/``d`` uint32).

    Args:
        state: ``(last_raw_time, wraps)`` carried from the previous chunk (-1 at the start).
        ahead: the records after these (a few), to tell a corrupt time near the chunk's end;
            at_end: nothing follows ``ahead``.
        corrupt: if given, one ``(record index, time µs, previous time µs, 0, count)`` is
            appended per run of records skipped for a corrupt time (:func:`clock_excursions`).
    Returns:
        ``(x, y, t, p, state_after)`` with t unwrapped to int64 µs.
    Raises:
        FormatError: a polarity other than 0/1.
    """
    raw_t = records["t"].astype(np.int64)
    d = records["d"]
    last_raw, wraps = state
    later = None if ahead is None else np.asarray(ahead["t"], np.int64)[:RETURN_WORDS]
    skip = clock_excursions(raw_t, last_raw, 1 << 32, CLOCK_JUMP_US, later, at_end)
    if skip.any():
        if corrupt is not None:
            for j in np.flatnonzero(skip & ~np.concatenate([[False], skip[:-1]])):
                run = j + int(np.argmin(skip[j:])) if not skip[j:].all() else len(skip)
                prev = int(raw_t[j - 1]) if j > 0 else max(last_raw, 0)
                corrupt.append((first_record + int(j), int(raw_t[j]), prev, 0, run - j))
        kept_at = np.flatnonzero(~skip)
        raw_t, d = raw_t[~skip], d[~skip]
    else:
        kept_at = None
    if len(raw_t):
        # uint32 µs wraps every 71.6 min: a big backward step is a wrap, a small one corruption.
        # Wraps are rare: find them, then add 2³² from each one on (no per-event cumsum)
        step = np.empty(len(raw_t), np.int64)
        step[0] = raw_t[0] - (last_raw if last_raw >= 0 else raw_t[0])
        np.subtract(raw_t[1:], raw_t[:-1], out=step[1:])
        at_wrap = np.flatnonzero(step < -(1 << 31))
        state_after = (int(raw_t[-1]), wraps + len(at_wrap))
        t = raw_t  # a fresh array (astype or a selection): changed in place
        if len(at_wrap) > 16:
            t += (wraps + np.cumsum(step < -(1 << 31))) << 32
        else:
            if wraps:
                t += wraps << 32
            for i in at_wrap:
                t[i:] += 1 << 32
    else:
        t, state_after = raw_t, state
    pol = (d >> 28).astype(np.uint8)
    if len(pol) and pol.max() > 1:
        i = int(np.flatnonzero(pol > 1)[0])
        at = i if kept_at is None else int(kept_at[i])
        raise FormatError(f"record {first_record + at} has polarity {int(pol[i])}, expected 0 "
                          "or 1 (corrupt file?)", path=path,
                          hint=_DAMAGED)
    # cast to 16 bits first: the masks then run over half the bytes
    x = d.astype(np.uint16) & np.uint16(0x3FFF)
    y = (d >> 14).astype(np.uint16) & np.uint16(0x3FFF)
    p = pol.view(np.int8) * np.int8(2) - np.int8(1)
    return x, y, t, p, state_after


#: clean .dat chunks are unpacked through views of the records' bytes, which read them as
#: little-endian: elsewhere every chunk takes the full decoding
_DAT_VIEWS = sys.byteorder == "little"
#: records per block of the clean-chunk passes: a block and its temporaries stay in the
#: processor's L2 cache between the passes over them (numpy makes one pass per operation)
DAT_BLOCK_EVENTS = 1 << 16


class _DatScratch:
    """Reused buffers of one pass over a .dat file (a block each)."""

    def __init__(self) -> None:
        self.block = np.empty(DAT_BLOCK_EVENTS, np.int64)  # records as read
        self.t = np.empty(DAT_BLOCK_EVENTS, np.uint32)
        self.d = np.empty(DAT_BLOCK_EVENTS, np.uint32)
        self.tmp = np.empty(DAT_BLOCK_EVENTS, np.uint32)
        self.rise = np.empty(DAT_BLOCK_EVENTS, bool)


class _DatJudge:
    """Whether a chunk's records need nothing of :func:`decode_dat_records` but the unpacking,
    judged block by block: their times never go back nor wrap, rise by at most
    :data:`CLOCK_JUMP_US` from the time before the chunk to its last (so that no time is a
    suspect for :func:`clock_excursions`), and every polarity is 0 or 1. A chunk that is not
    clean takes the full decoding, which repairs or raises as it always did.

    Also keeps the chunk's first and last time (raw) and largest column and row."""

    def __init__(self, last_raw: int, scratch: _DatScratch) -> None:
        self.last_raw = last_raw
        self.prev = last_raw  # the time before the next block
        self.first = -1
        self.n = 0
        self.xmax = self.ymax = 0
        self.clean = True
        self._s = scratch

    def feed(self, records: np.ndarray) -> bool:
        """Judge the next block (int64 array of records); False once the chunk is not clean."""
        m = len(records)
        s = self._s
        u32 = records.view(np.uint32)
        t, d = s.t[:m], s.d[:m]
        np.copyto(t, u32[0::2])  # contiguous copies: numpy is several times faster on them
        np.copyto(d, u32[1::2])
        if self.first < 0:
            self.first = int(t[0])
        self.clean = (int(t[0]) >= self.prev
                      and (m < 2 or bool(np.greater_equal(t[1:], t[:-1], out=s.rise[:m - 1])
                                         .all()))
                      and int(d.max()) < 2 << 28)
        if self.clean:
            self.xmax = max(self.xmax, int(np.bitwise_and(d, 0x3FFF, out=s.tmp[:m]).max()))
            self.ymax = max(self.ymax,
                            int(np.bitwise_and(d, 0x0FFFC000, out=s.tmp[:m]).max()) >> 14)
            self.prev = int(t[-1])
            self.n += m
        return self.clean

    def verdict(self) -> bool:
        """The chunk's judgement once every block was fed."""
        if not self.clean or self.n == 0 or (self.last_raw < 0 and self.n < 2):
            # a lone first record is judged by the records after it: the full decoding does it
            return False
        if self.last_raw >= 0 and self.first - self.last_raw > CLOCK_JUMP_US:
            return False
        return self.prev - self.first <= CLOCK_JUMP_US


def _unpack_clean_dat(records: np.ndarray, wraps: int, x: np.ndarray, y: np.ndarray,
                      t: np.ndarray, p: np.ndarray, scratch: _DatScratch) -> None:
    """Decode a block of a clean chunk (:class:`_DatJudge`) read into the int64 array
    ``records`` into the given arrays (t in µs). Equal, element for element, to
    :func:`decode_dat_records` on a clean chunk."""
    m = len(records)
    d, tmp = scratch.d[:m], scratch.tmp[:m]
    np.copyto(d, records.view(np.uint32)[1::2])
    np.copyto(x, d, casting="unsafe")  # the low 16 bits
    np.bitwise_and(x, 0x3FFF, out=x)
    np.right_shift(d, 14, out=tmp)
    np.copyto(y, tmp, casting="unsafe")
    np.bitwise_and(y, 0x3FFF, out=y)
    # polarity 0/1 (the chunk is clean: bits 29-31 are 0) → -1/+1
    np.greater_equal(d, 1 << 28, out=p.view(np.bool_))
    np.multiply(p, 2, out=p)
    np.subtract(p, 1, out=p)
    # the record's 8 bytes as a little-endian int64 are t + (d << 32): keep t
    np.bitwise_and(records, 0xFFFFFFFF, out=t)
    if wraps:
        np.add(t, wraps << 32, out=t)


class DatRecording(ChunkedRecording):
    """A Prophesee .dat file of CD events, decoded in chunks of :data:`DAT_CHUNK_EVENTS`.

    Files larger than the in-memory cache are indexed without being decoded: the index pass
    checks each chunk's times, polarities and coordinates on the raw records and keeps its time
    span, so that reading the events later decodes each chunk once, and the chunks it found
    clean with no check repeated. Chunks with something to repair (a wrap of the 32-bit clock,
    corrupt times) or to refuse take the full decoding in both passes.
    """

    gathers = True

    def __init__(self, path: Path, options: ReadOptions, chunk_events: int = DAT_CHUNK_EVENTS):
        from . import chunked

        header = _read_header(path)
        warnings: list[str] = []
        _ignore_time_unit(options, ".dat", warnings)
        width, height = _sensor(header, options, warnings, path)
        super().__init__(path, "dat", width, height, warnings)
        self.header = header
        with open(path, "rb") as fh:
            fh.seek(header.data_offset)
            kind = fh.read(2)
        if len(kind) < 2 or kind.startswith(b"%"):
            raise FormatError("the file has a header but no event type/size bytes (truncated?)",
                              path=path, hint=_DAMAGED)
        ev_type, ev_size = kind[0], kind[1]
        if ev_size != 8:
            raise FormatError(f"event size {ev_size} bytes, expected 8 (corrupt, or not a CD "
                              ".dat file?)", path=path,
                              hint=_DAMAGED)
        if ev_type not in (0x00, 0x0C):
            raise FormatError(f"event type 0x{ev_type:02X} is not CD events (0x0C)", path=path,
                              hint="only .dat files of CD (change detection) events are read")
        self._data_offset = header.data_offset + 2
        self._chunk = max(int(chunk_events), 1)
        self._num_records = _whole_records(path, self._data_offset, 8, "8-byte event record")
        self._corrupt: list[tuple[int, int, int, int, int]] = []
        #: per chunk ordinal, whether the index pass found it clean (None before that pass)
        self._clean: np.ndarray | None = None
        clean = np.zeros(-(-self._num_records // self._chunk), bool)
        self._counting = True
        # files the cache holds are decoded by the index pass, once; the others only checked
        summarize = self._num_records > chunked.CACHE_MAX_EVENTS
        self._build_index(self._pass(0, None, judged=clean, summarize=summarize))
        self._counting = False
        self._clean = clean
        if self._corrupt:
            first, to_us, from_us, _, _ = self._corrupt[0]
            self.warnings.append(_excursion_note(
                "record time", first, sum(c[4] for c in self._corrupt), to_us, from_us, 0,
                "record"))

    def _records_in(self, k: int) -> int:
        return min(self._chunk, self._num_records - k * self._chunk)

    def _read_into(self, fh, buf: np.ndarray) -> None:
        if fh.readinto(memoryview(buf).cast("B")) != buf.nbytes:
            raise FormatError("the file got shorter while it was read", path=self.path,
                              hint="read it again once nothing writes to it")

    def _full(self, fh, k: int, state: tuple[int, int]):
        """:func:`decode_dat_records` on chunk ``k``, with the records that follow it."""
        fh.seek(self._data_offset + 8 * k * self._chunk)
        rec = np.empty(self._records_in(k), np.int64)
        self._read_into(fh, rec)
        ahead = np.empty(RETURN_WORDS, _DAT_DTYPE)
        ahead = ahead[:fh.readinto(memoryview(ahead).cast("B")) // 8]
        end = (k + 1) * self._chunk + len(ahead) >= self._num_records
        return decode_dat_records(
            rec.view(_DAT_DTYPE), state, path=self.path, first_record=k * self._chunk,
            ahead=ahead, at_end=end, corrupt=self._corrupt if self._counting else None)

    def _unpack(self, fh, k: int, wraps: int, x: np.ndarray, y: np.ndarray, t: np.ndarray,
                p: np.ndarray, scratch: _DatScratch) -> None:
        """Unpack clean chunk ``k`` into the arrays given (its length), block by block: each
        block read into the scratch buffer, where it stays in the cache for the passes over
        it."""
        fh.seek(self._data_offset + 8 * k * self._chunk)
        for i in range(0, len(t), DAT_BLOCK_EVENTS):
            s = slice(i, i + DAT_BLOCK_EVENTS)
            block = scratch.block[:len(t[s])]
            self._read_into(fh, block)
            _unpack_clean_dat(block, wraps, x[s], y[s], t[s], p[s], scratch)

    def _pass(self, start: int, resume: Any, *, judged: np.ndarray | None = None,
              summarize: bool = False) -> Iterator[Chunk | ChunkSummary]:
        """Chunks from ``start`` in file order. While indexing (``judged`` given), every chunk
        is judged and ``judged`` filled in; with ``summarize`` a clean chunk is only checked
        and summed up. Afterwards the index's judgement is used."""
        state = (-1, 0) if resume is None else resume
        scratch = _DatScratch()
        with open(self.path, "rb") as fh:
            for k in range(start, -(-self._num_records // self._chunk)):
                n = self._records_in(k)
                if judged is None:
                    clean = bool(self._clean[k])  # type: ignore[index]
                elif not _DAT_VIEWS:
                    clean = False
                else:
                    judge = _DatJudge(state[0], scratch)
                    fh.seek(self._data_offset + 8 * k * self._chunk)
                    for i in range(0, n, DAT_BLOCK_EVENTS):
                        block = scratch.block[:min(DAT_BLOCK_EVENTS, n - i)]
                        self._read_into(fh, block)
                        if not judge.feed(block):
                            break
                    judged[k] = clean = judge.verdict()
                if not clean:
                    x, y, t, p, after = self._full(fh, k, state)
                    yield Chunk(k, x, y, t, p, resume=state)
                    state = after
                    continue
                wraps = state[1]
                if summarize:
                    yield ChunkSummary(k, judge.first + (wraps << 32), judge.prev + (wraps << 32),
                                       n, judge.xmax, judge.ymax, resume=state)
                    state = (judge.prev, wraps)
                    continue
                x, y = np.empty(n, np.uint16), np.empty(n, np.uint16)
                t, p = np.empty(n, np.int64), np.empty(n, np.int8)
                self._unpack(fh, k, wraps, x, y, t, p, scratch)
                yield Chunk(k, x, y, t, p, resume=state)
                state = (int(t[-1]) - (wraps << 32), wraps)

    def _decode(self, start: int = 0, resume: Any = None) -> Iterator[Chunk]:
        return self._pass(start, resume)  # type: ignore[return-value]

    def _gather(self, k0: int, k1: int) -> EventStream:
        """The events of the index's chunks k0..k1 in one set of arrays, clean chunks
        unpacked straight into it."""
        total = int(self._count[k0:k1 + 1].sum())
        x, y = np.empty(total, np.uint16), np.empty(total, np.uint16)
        t, p = np.empty(total, np.int64), np.empty(total, np.int8)
        scratch = _DatScratch()
        at = 0
        with open(self.path, "rb") as fh:
            for i in range(k0, k1 + 1):
                k, state = int(self._ordinal[i]), self._resume[i]
                s = slice(at, at + int(self._count[i]))
                if self._clean[k]:  # type: ignore[index]
                    self._unpack(fh, k, state[1], x[s], y[s], t[s], p[s], scratch)
                else:
                    x[s], y[s], t[s], p[s], _ = self._full(fh, k, state)
                at = s.stop
        return EventStream(x, y, t, p, self.width, self.height)


def read_dat(path: Path, options: ReadOptions) -> DatRecording:
    """Open a Prophesee .dat file of CD events (indexed on open, decoded per window)."""
    return DatRecording(Path(path), options)


# -- EVT 3.0 ---------------------------------------------------------------------------------


class _AfterScan:
    """An attribute of :class:`Evt3Recording` that a scan still running may yet set or change
    (the index, the warnings): reading it waits for the scan."""

    def __set_name__(self, owner, name: str) -> None:
        self.key = "_scanned" + name

    def __get__(self, obj, owner=None):
        if obj is None:
            return self
        obj._settle_scan()
        return obj.__dict__[self.key]

    def __set__(self, obj, value) -> None:
        obj.__dict__[self.key] = value


class _Failed:
    """A scan that raised: ``result()`` raises its error again."""

    def __init__(self, error: Exception) -> None:
        self.error = error

    def result(self):
        raise self.error


class Evt3Recording(ChunkedRecording):
    """An EVT 3.0 .raw file, decoded by the ``evt3`` package.

    EVT 3.0 keeps decoder state across the whole stream. Bodies up to :data:`EVT3_EAGER_BYTES`
    are decoded when opened (every event checked; kept in memory when they fit the cache).
    Larger ones open on a scan of their raw words (:mod:`trmd_cli.read.evt3_words`: the time
    words give each segment's time bounds, the clock's wraps and points the decoder can start
    at), so they are decoded once, as they are read; their events are checked (times in order,
    coordinates inside the sensor) as each segment is decoded, and the event count is known
    only after a pass (``num_events`` makes one). That scan runs on a thread of its own
    (:func:`~trmd_cli.threads.beside`) while the caller goes on: what needs the index, or the
    warnings, waits for it, and what it refuses (no time word, the clock going back) is raised
    by the first read; the whole file, read first, is decoded meanwhile (the decoder releases
    the interpreter), which costs the scan's fifth of a decoding no more.
    """

    gathers = True
    _scan = _AfterScan()
    _ordinal = _AfterScan()
    _first = _AfterScan()
    _last = _AfterScan()
    _resume = _AfterScan()
    warnings = _AfterScan()

    def __init__(self, path: Path, options: ReadOptions, batch_bytes: int = EVT3_CHUNK_BYTES,
                 eager_bytes: int | None = None):
        from . import require

        self._evt3 = require("evt3", path=path)
        header = _read_header(path)
        if header.encoding not in (None, "evt3"):
            raise FormatError(f"the header says {header.encoding}, not EVT 3.0", path=path,
                              hint="check the '% evt' / '% format' header lines")
        warnings: list[str] = []
        _ignore_time_unit(options, "EVT 3.0", warnings)
        width, height = _sensor(header, options, warnings, path)
        super().__init__(path, "evt3", width, height, warnings)
        self.header = header
        self._batch_bytes = int(batch_bytes)
        self._words = words = _whole_records(path, header.data_offset, 2, "16-bit word")
        eager = EVT3_EAGER_BYTES if eager_bytes is None else int(eager_bytes)
        self._range: tuple[int, int] | None = None
        self._events: int | None = None
        self._lazy = not (2 * words <= eager or width is None or height is None)
        self._scan_lock = threading.RLock()
        if self._lazy:
            # the scan runs beside whatever is read first: a read of the whole file needs no
            # index and decodes meanwhile (the decoder releases the interpreter); anything
            # that needs the index waits for it (:class:`_AfterScan`)
            self.gathers = False
            self._pending = beside(scan_evt3, path, header.data_offset, words)
        else:
            self._pending = None
            self._take_scan(scan_evt3(path, header.data_offset, words))
            self._build_index()

    def _take_scan(self, scan: Evt3Scan) -> None:
        """What the scan says of the file: refused without a time word, its undefined words
        noted, and (opened lazily) the index of its segments."""
        if self._words and scan.first_time_word < 0:
            # the decoder decodes no event before the first TIME_HIGH (type 0x8, sent every
            # 4 ms whatever the scene): bytes without one are not a recording
            raise FormatError(f"the header promises EVT 3.0 but its {2 * self._words}-byte body "
                              "holds no event and no time word", path=self.path, hint=_DAMAGED)
        if scan.undefined:
            count, first, kinds = scan.undefined
            self.warnings.append(
                f"{count} word(s) of type{'s' if len(kinds) > 1 else ''} "
                f"{', '.join(f'0x{k:X}' for k in kinds)}, which EVT 3.0 does not define, were "
                f"skipped (the first is word {first}): a damaged file? the events around them "
                "may be wrong")
        if self._lazy:
            self._scan = scan
            self._ordinal = np.arange(len(scan.starts), dtype=np.int64)
            self._first, self._last = scan.lo_us, scan.hi_us
            self._resume = [(int(a), int(w)) for a, w in zip(scan.starts, scan.wraps,
                                                             strict=True)]
        else:
            self._scan = None

    def _settle_scan(self) -> None:
        """Wait for the scan started on opening (once; its error, if any, every time)."""
        with self._scan_lock:
            pending = self.__dict__.get("_pending")
            if pending is None:
                return
            self._pending = None  # (taking the scan reads the warnings: no second wait)
            try:
                self._take_scan(pending.result())
            except FormatError as e:
                self._pending = _Failed(e)
                raise

    @contextlib.contextmanager
    def _decoder_errors(self) -> Iterator[None]:
        """The decoder's errors as one line about the file."""
        try:
            yield
        except (OSError, ValueError, RuntimeError) as e:
            raise FormatError(f"EVT 3.0 decoding failed: {e}", path=self.path,
                              hint=_DAMAGED) from None

    def _decode(self, start: int = 0, resume: Any = None) -> Iterator[Chunk]:
        with self._decoder_errors():
            if self._lazy:
                yield from self._decode_segments(start)
                return
            batches = self._evt3.decode_file_batches(str(self.path), batch_bytes=self._batch_bytes)
            for k, ev in enumerate(batches):
                if k < start:
                    continue
                yield self._chunk(k, ev, 0)

    @staticmethod
    def _chunk(k: int, ev, offset_us: int) -> Chunk:
        t = np.asarray(ev.t)
        # times are far below 2**63: reinterpret instead of copying
        t = t.view(np.int64) if t.dtype == np.uint64 else t.astype(np.int64)
        if offset_us:
            t += offset_us
        # polarity 0/1 → -1/+1 in one new array (int8 arithmetic wraps as the casts before did)
        p = np.multiply(np.asarray(ev.p).view(np.int8), 2, dtype=np.int8)
        np.subtract(p, 1, out=p)
        return Chunk(k, np.asarray(ev.x, np.uint16), np.asarray(ev.y, np.uint16), t, p)

    def _decode_segments(self, start: int) -> Iterator[Chunk]:
        """The scan's segments from ``start`` on, one chunk each, decoded by one decoder fed
        segment after segment and checked as they come."""
        scan = self._scan
        assert scan is not None
        offset = self.header.data_offset
        ends = np.append(scan.starts[1:], self._words)
        decoder = self._evt3.Decoder(sensor_width=self.width, sensor_height=self.height)
        # the decoder counts the wraps it sees; those before its first word are added
        offset_us = int(scan.wraps[start]) << 24
        last = -1
        with open(self.path, "rb") as fh:
            for k in range(start, len(scan.starts)):
                a, b = int(scan.starts[k]), int(ends[k])
                fh.seek(offset + 2 * a)
                raw = fh.read(2 * (b - a))
                if k == start and k > 0:
                    # after the segment's TIME_HIGH, the row and vector column there
                    prefix = resume_prefix(fh, offset, a, scan.first_time_word)
                    raw = raw[:2] + prefix.tobytes() + raw[2:]
                ch = self._chunk(k, decoder.feed(raw), offset_us)
                if len(ch.t):
                    self._check(ch, last)
                    last = int(ch.t[-1])
                yield ch

    def _check(self, ch: Chunk, last: int) -> None:
        """What the index pass checks of a decoded chunk, for a chunk decoded after opening
        (``last``: the time of the event before it, −1 for none)."""
        t = ch.t
        if int(t[0]) < last or (len(t) > 1 and bool(np.less(t[1:], t[:-1]).any())):
            i = 0 if int(t[0]) < last else int(np.flatnonzero(np.diff(t) < 0)[0]) + 1
            before = last if i == 0 else int(t[i - 1])
            raise FormatError(f"an event at {int(t[i])} µs follows one at {before} µs: it goes "
                              "back in time (corrupt file?)", path=self.path,
                              hint=IN_ORDER_HINT)
        self._check_inside(int(ch.x.max()), int(ch.y.max()))

    def _one_chunk(self, k: int) -> Chunk:
        with contextlib.closing(self._decode(k, self._resume[k])) as source:
            return next(source)

    def time_range_us(self) -> tuple[int, int]:
        if not self._lazy:
            return super().time_range_us()
        if self._range is None:
            with contextlib.closing(self._decode(0)) as source:
                first = next((int(c.t[0]) for c in source if len(c.t)), None)
            last = first
            for k in range(len(self._ordinal) - 1, -1, -1) if first is not None else ():
                ch = self._one_chunk(k)
                if len(ch.t):
                    last = int(ch.t[-1])
                    break
            if first is None:
                self._range, self._events = (0, 0), 0
            else:
                self._range = (first, int(last))
        return self._range

    def is_empty(self) -> bool:
        if not self._lazy:
            return super().is_empty()
        self.time_range_us()
        return self._events == 0

    def num_events(self) -> int:
        if not self._lazy:
            return super().num_events()
        if self._events is None:
            with contextlib.closing(self._decode(0)) as source:
                self._events = sum(len(c.t) for c in source)
        return self._events

    def events(self, start_us: float | None = None, end_us: float | None = None) -> EventStream:
        if not self._lazy:
            return super().events(start_us, end_us)
        lo = -np.inf if start_us is None else start_us
        hi = np.inf if end_us is None else end_us
        if start_us is None and end_us is None:
            return self._whole(lo, hi)  # no index needed: decoded while the scan runs
        sel = np.flatnonzero((self._last >= lo) & (self._first < hi))
        if len(sel) <= 2:
            return super().events(start_us, end_us)
        if sel[0] == 0 and sel[-1] == len(self._ordinal) - 1:
            return self._whole(lo, hi)
        # a long span: each segment's part as it is decoded, joined at the end (the windows
        # kept for requests that move forward would hold the whole span a second time)
        parts: list[Chunk] = []
        with contextlib.closing(self._decode(int(sel[0]), self._resume[int(sel[0])])) as source:
            for ch in source:
                parts.append(ch)
                if ch.ordinal >= sel[-1]:
                    break
        return self._window(parts, lo, hi)

    def _whole(self, lo: float, hi: float) -> EventStream:
        """The events of the whole file within ``[lo, hi)``: the decoder's one call writes
        straight into the arrays returned."""
        with self._decoder_errors():
            ch = self._chunk(0, self._evt3.decode_file(str(self.path)), 0)
        self._settle_scan()  # what the scan refuses (no time word, the clock going back) first
        if len(ch.t):
            self._check(ch, -1)
        self._events = len(ch.t)
        ev = EventStream(ch.x, ch.y, ch.t, ch.p, self.width, self.height)
        return ev.take(time_slice(ev.t, lo, hi))


def read_evt3(path: Path, options: ReadOptions) -> Evt3Recording:
    """Open a Prophesee EVT 3.0 .raw file (decoded with the ``evt3`` package)."""
    return Evt3Recording(Path(path), options)
