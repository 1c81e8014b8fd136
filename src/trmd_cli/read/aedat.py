"""jAER / cAER recordings: AEDAT 2.0 and AEDAT 3.1, decoded here with numpy.

Written from iniVation's format descriptions ("AEDAT 2.0", "AEDAT 3.1") and from the code that
writes and plays these files (jAER's ``DVS128`` / ``DavisBaseCamera`` extractors, libcaer's
event structures). Units and conventions:

* time: microseconds on the camera's clock, kept as they are (nothing is subtracted);
* x = column, y = row, (0, 0) at the top-left; polarity ON = +1, OFF = -1.

**AEDAT 2.0** (``#!AER-DAT2.0``): ``#`` header lines (ending at ``#End Of ASCII Header`` or at
the first line that is not one), then big-endian records ``int32 address, int32 timestamp``
(µs; the 32-bit counter is unwrapped). The address layout is the chip's, named by the header's
``# AEChip:`` line:

* DVS128 (``DVS128``, ``Tmpdiff128``): bit 0 polarity, bits 1–7 x, bits 8–14 y, bit 15 an
  external event. As jAER and libcaer read it: raw polarity 0 is ON, x = 127 − raw x, and jAER's
  y counts from the bottom, so y = 127 − raw y.
* DAVIS (``DAVIS240A/B/C`` 240×180, ``Davis346*`` 346×260, ``DAVIS128`` 128×128, ``Davis640``
  640×480, ``Davis208`` 208×192): bit 31 clear is a DVS event — y in bits 22–30, x in bits
  12–21, polarity in bit 11 (1 = ON), bit 10 set for an external-input event; bit 31 set is an
  APS sample — the same x/y bits, readout type in bits 10–11 (0 reset read, 1 signal read, 3
  with bit 31 an IMU word), the 10-bit ADC value in bits 0–9. jAER mirrors DVS x
  (``sizeX − 1 − x``), not APS x, and draws y from the bottom: DVS x = W − 1 − raw x, APS x =
  raw x, and y = H − 1 − raw y for both.
* APS frames (DAVIS, global shutter): a frame is a run of reset reads followed by a run of
  signal reads; its pixels are reset − signal (clipped at 0) / 1023; its exposure runs from the
  last reset read to the first signal read, as in jAER. A frame that does not read every pixel
  once (rolling shutter, a region of interest, a cut) is skipped with a warning.

**AEDAT 3.1** (``#!AER-DAT3.1``, cAER / DV): header lines up to ``#!END-HEADER``, then packets:
a 28-byte little-endian header (int16 eventType, int16 eventSource, int32 eventSize, int32
eventTSOffset, int32 eventTSOverflow, int32 eventCapacity, int32 eventNumber, int32 eventValid)
and eventCapacity × eventSize bytes of events, of which the first eventNumber are used. Time is
``eventTSOverflow · 2³¹ + timestamp``.

* polarity events (type 1, 8 bytes): uint32 data — bit 0 valid, bit 1 polarity, y in bits
  2–16, x in bits 17–31 — and int32 timestamp;
* frame events (type 2): uint32 info (bit 0 valid, bits 1–3 channels: 1 gray, 3 RGB, 4 RGBA),
  int32 start/end of frame, int32 start/end of exposure, int32 lengthX, lengthY, positionX,
  positionY, then lengthX × lengthY × channels uint16 pixels, row by row from the top
  (/ 65535); the exposure window is [start of exposure, end of exposure] µs;
* events marked invalid are skipped (counted); other event types (special, IMU, …) are skipped
  with one warning naming them. When several sources hold events or frames, the first of each
  is read (warned).

Both files are indexed in one pass when opened (checking every record, noting frame
exposures without keeping pixels); windows are then read by seeking to the chunk that holds
them (:class:`~trmd_cli.read.chunked.ChunkedRecording`), frames decoded one at a time.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError, InputError
from ..events import Exposure
from .base import Frame, ReadOptions
from .chunked import Chunk, ChunkedRecording
from .stamps import pixels_to_float

__all__ = ["read_aedat2", "read_aedat3", "Aedat2Recording", "Aedat3Recording",
           "parse_aedat_header", "AedatHeader", "AEDAT2_CHUNK_RECORDS", "AEDAT3_CHUNK_EVENTS",
           "chip_layout"]

#: AEDAT 2.0 records decoded per chunk (8 MiB)
AEDAT2_CHUNK_RECORDS = 1 << 20
#: AEDAT 3.1 polarity events gathered per chunk (whole packets)
AEDAT3_CHUNK_EVENTS = 1 << 20
#: most header bytes looked at (jAER may dump its preferences, ~100 KB, into the header)
_HEADER_MAX = 32 << 20

_DAMAGED = "the file may be incomplete or damaged: copy it again or re-export the recording"

#: jAER chip classes (last part of the AEChip name, lower case, fragment) → layout and size
_CHIPS = (("dvs128", "dvs128", (128, 128)), ("tmpdiff128", "dvs128", (128, 128)),
          ("davis240", "davis", (240, 180)), ("davis346", "davis", (346, 260)),
          ("davis128", "davis", (128, 128)), ("davis640", "davis", (640, 480)),
          ("davis208", "davis", (208, 192)))

#: AEDAT 3.1 source names (``#Source 1: DAVIS346B``) → sensor size
_SOURCES = (("dvs128", (128, 128)), ("davis240", (240, 180)), ("davis346", (346, 260)),
            ("davis128", (128, 128)), ("davis640", (640, 480)), ("davis208", (208, 192)),
            ("dvxplorer", (640, 480)))

#: AEDAT 3.1 event type numbers → names, for the warning about what was skipped
_TYPES = {0: "special", 1: "polarity", 2: "frame", 3: "IMU6", 4: "IMU9", 5: "sample",
          6: "ear", 7: "config", 8: "point1D", 9: "point2D", 10: "point3D", 11: "point4D",
          12: "spike", 13: "matrix4x4"}

_AEDAT3_HEADER = np.dtype([("type", "<i2"), ("source", "<i2"), ("size", "<i4"),
                           ("ts_offset", "<i4"), ("overflow", "<i4"), ("capacity", "<i4"),
                           ("number", "<i4"), ("valid", "<i4")])
_POLARITY3 = np.dtype([("data", "<u4"), ("t", "<i4")])
_FRAME3 = np.dtype([("info", "<u4"), ("start_frame", "<i4"), ("end_frame", "<i4"),
                    ("start_exposure", "<i4"), ("end_exposure", "<i4"), ("length_x", "<i4"),
                    ("length_y", "<i4"), ("position_x", "<i4"), ("position_y", "<i4")])
_RECORD2 = np.dtype([("a", ">u4"), ("t", ">u4")])


# -- header -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class AedatHeader:
    """The text header of an AEDAT 2.0 / 3.x file.

    Attributes:
        version: ``"2.0"``, ``"3.1"`` … from the first line.
        lines: every header line without ``#`` and line ending.
        data_offset: byte offset where the binary data starts.
    """

    version: str
    lines: tuple[str, ...] = ()
    data_offset: int = 0

    def value(self, key: str) -> str | None:
        """The text after ``key:`` in the first line that starts with it (case-insensitive)."""
        k = key.lower()
        for line in self.lines:
            s = line.strip()
            if s.lower().startswith(k):
                rest = s[len(k):].lstrip()
                return rest[1:].strip() if rest.startswith(":") else rest.strip()
        return None


def parse_aedat_header(path: Path) -> AedatHeader:
    """Read the ``#`` header lines of an AEDAT 2.0 / 3.x file.

    AEDAT 3.x ends its header with ``#!END-HEADER``; AEDAT 2.0 with ``#End Of ASCII Header``
    or, in older files, at the first line that is not a printable ``#`` line.

    Raises:
        FormatError: no version line, or a 3.x header without its end line.
    """
    lines: list[str] = []
    with open(path, "rb") as fh:
        first = fh.readline(256)
        m = re.match(rb"#!AER-DAT(\d+\.\d+)\r?\n", first)
        if not m:
            raise FormatError("not an AEDAT file (no '#!AER-DATx.y' first line)", path=path,
                              hint=_DAMAGED)
        version = m[1].decode()
        pos = len(first)
        three = version.startswith("3")
        while pos < _HEADER_MAX:
            line = fh.readline(1 << 20)
            if not line:
                if three:
                    raise FormatError("the file ends inside its header (no '#!END-HEADER' "
                                      "line: truncated?)", path=path, hint=_DAMAGED)
                break
            if not line.startswith(b"#") or not line.endswith(b"\n") or not _printable(line):
                if three:
                    raise FormatError("the header has no '#!END-HEADER' line (truncated or "
                                      "corrupt?)", path=path, hint=_DAMAGED)
                break
            pos += len(line)
            text = line[1:].rstrip(b"\r\n").decode("latin-1")
            if three and text.startswith("!END-HEADER"):
                break
            lines.append(text)
            if not three and text.strip().lower() == "end of ascii header":
                break
    return AedatHeader(version, tuple(lines), pos)


def _printable(line: bytes) -> bool:
    body = line.rstrip(b"\r\n")
    return all(c >= 0x20 or c == 0x09 for c in body) and b"\x7f" not in body


def chip_layout(chip: str | None) -> tuple[str, tuple[int, int]] | None:
    """``"dvs128"`` / ``"davis"`` and (W, H) for a jAER AEChip class name, or None."""
    if not chip:
        return None
    name = chip.strip().rsplit(".", 1)[-1].lower()
    for fragment, layout, size in _CHIPS:
        if fragment in name:
            return layout, size
    return None


def _ignore_time_unit(options: ReadOptions, warnings: list[str]) -> None:
    if options.time_unit not in (None, "us"):
        warnings.append(f"`time_unit={options.time_unit!r}` ignored: AEDAT times are "
                        "microseconds by specification")


# -- AEDAT 2.0 --------------------------------------------------------------------------------


@dataclass
class _Aps2Frame:
    """What the index pass knows of one AEDAT 2.0 APS frame (no pixels)."""

    first_record: int
    exposure: Exposure | None


class _ApsAssembler:
    """Turns AEDAT 2.0 APS samples into frames, chunk after chunk (state kept between calls).

    A frame is a run of reset reads and the run of signal reads after it; it is complete when
    every pixel was read once in each. Frames come out as (first record index, exposure or
    None, image or None) when the next frame starts or at :meth:`finish`.
    """

    def __init__(self, width: int, height: int, keep_pixels: bool) -> None:
        self.w, self.h = width, height
        self.keep = keep_pixels
        self.incomplete = 0
        self._open = False
        self._phase = 0  # 0 reset reads, 1 signal reads
        self._reset_seen = np.zeros(width * height, bool)
        self._signal_seen = np.zeros(width * height, bool)
        self._reset = np.zeros(width * height, np.int32) if keep_pixels else None
        self._signal = np.zeros(width * height, np.int32) if keep_pixels else None
        self._first = 0
        self._last_reset_t = 0
        self._first_signal_t: int | None = None
        self._dup = False

    def feed(self, rec_index: np.ndarray, kind: np.ndarray, pix: np.ndarray, adc: np.ndarray,
             t: np.ndarray) -> list[tuple[int, Exposure | None, np.ndarray | None]]:
        """APS samples of one chunk in file order: kind 0 reset, 1 signal; pix = y·W + x."""
        out: list[tuple[int, Exposure | None, np.ndarray | None]] = []
        if len(kind) == 0:
            return out
        prev = np.concatenate([[self._phase if self._open else 1], kind[:-1]])
        starts = np.flatnonzero((kind == 0) & (prev == 1))  # a reset after signals: new frame
        bounds = [0, *starts.tolist(), len(kind)]
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            if a == b:
                continue
            if kind[a] == 0 and (not self._open or self._phase == 1):
                done = self._close()
                if done is not None:
                    out.append(done)
                self._start(int(rec_index[a]))
            if not self._open:  # signal reads before any reset read: no frame to go with
                self.incomplete += 1
                continue
            self._take(kind[a:b], pix[a:b], adc[a:b], t[a:b])
        return out

    def finish(self) -> list[tuple[int, Exposure | None, np.ndarray | None]]:
        done = self._close()
        return [] if done is None else [done]

    def _start(self, first: int) -> None:
        self._open, self._phase, self._first = True, 0, first
        self._reset_seen[:] = False
        self._signal_seen[:] = False
        self._first_signal_t = None
        self._dup = False

    def _take(self, kind, pix, adc, t) -> None:
        resets = kind == 0
        for is_reset, seen, store in ((True, self._reset_seen, self._reset),
                                      (False, self._signal_seen, self._signal)):
            sel = resets if is_reset else ~resets
            if not sel.any():
                continue
            p = pix[sel]
            if seen[p].any() or len(np.unique(p)) != len(p):
                self._dup = True
            seen[p] = True
            if store is not None:
                store[p] = adc[sel]
            if is_reset:
                self._last_reset_t = int(t[sel][-1])
            elif self._first_signal_t is None:
                self._first_signal_t = int(t[sel][0])
        if (~resets).any():
            self._phase = 1

    def _close(self) -> tuple[int, Exposure | None, np.ndarray | None] | None:
        if not self._open:
            return None
        self._open = False
        if self._dup or not (self._reset_seen.all() and self._signal_seen.all()):
            self.incomplete += 1
            return None
        t0, t1 = self._last_reset_t, self._first_signal_t
        exposure = Exposure(t0, t1) if t1 is not None and t1 > t0 else None
        image = None
        if self.keep:
            assert self._reset is not None and self._signal is not None
            cds = np.clip(self._reset - self._signal, 0, 1023).reshape(self.h, self.w)
            image = (cds.astype(np.float32) / 1023.0)
        return self._first, exposure, image


class Aedat2Recording(ChunkedRecording):
    """An AEDAT 2.0 file (jAER): DVS events (chunked by records) and, for DAVIS, APS frames."""

    def __init__(self, path: Path, options: ReadOptions) -> None:
        warnings: list[str] = []
        self.header = parse_aedat_header(path)
        _ignore_time_unit(options, warnings)
        chip = self.header.value("AEChip")
        found = chip_layout(chip)
        offset = self.header.data_offset
        total = os.path.getsize(path)
        n, rest = divmod(total - offset, 8)
        if rest:
            raise FormatError(f"the file ends with {rest} byte(s) of a partial record "
                              "(truncated?)", path=path,
                              hint=f"if the recording was interrupted, keep its complete part: "
                                   f"truncate -s {total - rest} FILE (on a copy)")
        self._records = n
        if found is None:
            layout = self._guess_layout(path, offset, n)
            what = f"the AEChip line names {chip!r}" if chip else "the header names no AEChip"
            if layout == "dvs128":
                size = (128, 128)
                warnings.append(f"{what}: reading the addresses as a DVS128's (128x128)")
            elif options.sensor is not None:
                size = tuple(options.sensor)  # type: ignore[assignment]
                warnings.append(f"{what}: reading the addresses as a DAVIS's, "
                                f"{size[0]}x{size[1]} from `sensor`")
            else:
                raise InputError(f"{what}; its addresses are a DAVIS's, whose size trmd must "
                                 "know to place them", path=path,
                                 hint="pass `sensor=(W, H)`, e.g. 346x260 or 240x180")
        else:
            layout, size = found
            if options.sensor is not None and tuple(options.sensor) != size:
                warnings.append(f"`sensor={tuple(options.sensor)}` ignored: the header names a "
                                f"{chip} ({size[0]}x{size[1]})")
        self.layout = layout
        self.chip = chip
        super().__init__(path, "aedat2", size[0], size[1], warnings)
        self._skipped: dict[str, int] = {}
        self._frames: list[_Aps2Frame] = []
        self._incomplete = 0
        self._build_index(self._first_pass())
        self._note()

    @staticmethod
    def _guess_layout(path: Path, offset: int, n: int) -> str:
        """DVS128 addresses fit 16 bits; DAVIS put x and y above bit 12."""
        with open(path, "rb") as fh:
            fh.seek(offset)
            rec = np.frombuffer(fh.read(8 * min(n, 1 << 16)), _RECORD2)
        return "dvs128" if len(rec) == 0 or int(rec["a"].max()) < 0x10000 else "davis"

    # -- decoding -----------------------------------------------------------------------------

    def _records_from(self, start: int, resume: Any) -> Iterator[tuple[int, np.ndarray,
                                                                       np.ndarray]]:
        """(chunk number, addresses, unwrapped times µs) per chunk, from chunk ``start``.

        ``resume`` = (first record, wraps so far, last raw time) of chunk ``start``; without it
        the file is read from its start (unwrapping needs every earlier time) and the chunks
        before ``start`` are skipped."""
        if resume is None:
            first, wraps, last, skip = 0, 0, None, start
        else:
            (first, wraps, last), skip = resume, 0
        k = first // AEDAT2_CHUNK_RECORDS
        with open(self.path, "rb") as fh:
            fh.seek(self.header.data_offset + 8 * first)
            while True:
                buf = fh.read(8 * AEDAT2_CHUNK_RECORDS)
                if not buf:
                    return
                if len(buf) % 8:
                    raise FormatError("the file changed while it was read", path=self.path,
                                      hint=_DAMAGED)
                rec = np.frombuffer(buf, _RECORD2)
                raw = rec["t"].astype(np.int64)
                prev = np.concatenate([[raw[0] if last is None else last], raw[:-1]])
                back = (raw - prev) < -(1 << 31)  # the 32-bit counter wrapped
                t = raw + ((wraps + np.cumsum(back)) << 32)
                wraps += int(back.sum())
                last = int(raw[-1])
                if k >= skip:
                    yield k, rec["a"].astype(np.uint32), t
                k += 1

    def _dvs(self, k: int, a: np.ndarray, t: np.ndarray, count: bool) -> tuple[Chunk, Any]:
        w, h = self.width, self.height
        if self.layout == "dvs128":
            special = a >= 0x8000
            ev = ~special
            rx = (a[ev] >> 1) & 0x7F
            ry = (a[ev] >> 8) & 0x7F
            x, y = 127 - rx, 127 - ry
            p = np.where((a[ev] & 1) == 0, 1, -1).astype(np.int8)
            if count and special.any():
                self._skip("external (special) events", int(special.sum()))
        else:
            aps = (a & 0x80000000) != 0
            ext = ~aps & ((a & 0x400) != 0)
            ev = ~aps & ~ext
            rx = (a[ev] >> 12) & 0x3FF
            ry = (a[ev] >> 22) & 0x1FF
            if len(rx) and (int(rx.max()) >= w or int(ry.max()) >= h):
                axis, v = ("x", int(rx.max())) if int(rx.max()) >= w else ("y", int(ry.max()))
                raise FormatError(f"a DVS event has {axis} address {v}, outside the {w}x{h} "
                                  f"sensor of the {self.chip or 'DAVIS'} (corrupt file, or "
                                  "another chip?)", path=self.path,
                                  hint="check the header's AEChip line, or `sensor=(W, H)`")
            x, y = (w - 1) - rx.astype(np.int64), (h - 1) - ry.astype(np.int64)
            p = np.where((a[ev] & 0x800) != 0, 1, -1).astype(np.int8)
            if count and ext.any():
                self._skip("external-input events", int(ext.sum()))
        return Chunk(k, x.astype(np.uint16), y.astype(np.uint16), t[ev], p,
                     None), ev

    def _aps(self, a: np.ndarray, t: np.ndarray, first: int, count: bool):
        """APS samples of a chunk: (record index, kind, pixel, adc, t) of resets/signals."""
        aps = (a & 0x80000000) != 0
        imu = (a & 0x80000C00) == 0x80000C00
        kind = (a >> 10) & 3
        if count:
            if imu.any():
                self._skip("IMU samples", int(imu.sum()))
            other = aps & ~imu & (kind == 2)
            if other.any():
                self._skip("APS samples of the third (C) readout", int(other.sum()))
        sel = aps & ~imu & (kind < 2)
        idx = np.flatnonzero(sel)
        if len(idx) == 0:
            return None
        s = a[idx]
        rx = (s >> 12) & 0x3FF
        ry = (s >> 22) & 0x1FF
        w, h = self.width, self.height
        if int(rx.max()) >= w or int(ry.max()) >= h:
            raise FormatError(f"an APS sample addresses pixel ({int(rx.max())}, "
                              f"{int(ry.max())}), outside the {w}x{h} sensor", path=self.path,
                              hint="check the header's AEChip line, or `sensor=(W, H)`")
        pix = ((h - 1) - ry.astype(np.int64)) * w + rx.astype(np.int64)
        return (first + idx, kind[idx].astype(np.int8), pix, (s & 0x3FF).astype(np.int32),
                t[idx])

    def _skip(self, what: str, n: int) -> None:
        self._skipped[what] = self._skipped.get(what, 0) + n

    def _first_pass(self) -> Iterator[Chunk]:
        asm = _ApsAssembler(self.width, self.height, keep_pixels=False) \
            if self.layout == "davis" else None
        state: tuple[int, int, int | None] = (0, 0, None)
        for k, a, t in self._records_from(0, None):
            chunk, _ = self._dvs(k, a, t, count=True)
            yield Chunk(chunk.ordinal, chunk.x, chunk.y, chunk.t, chunk.p, state)
            # where the next chunk resumes: its first record, the wraps so far, the last raw time
            state = ((k + 1) * AEDAT2_CHUNK_RECORDS, int(t[-1]) >> 32, int(t[-1]) & 0xFFFFFFFF)
            if asm is not None:
                samples = self._aps(a, t, k * AEDAT2_CHUNK_RECORDS, count=True)
                if samples is not None:
                    for first_rec, exp, _ in asm.feed(*samples):
                        self._frames.append(_Aps2Frame(first_rec, exp))
        if asm is not None:
            for first_rec, exp, _ in asm.finish():
                self._frames.append(_Aps2Frame(first_rec, exp))
            self._incomplete = asm.incomplete

    def _decode(self, start: int = 0, resume: Any = None) -> Iterator[Chunk]:
        for k, a, t in self._records_from(start, resume):
            chunk, _ = self._dvs(k, a, t, count=False)
            yield chunk

    def _note(self) -> None:
        if self._skipped:
            parts = ", ".join(f"{n} {what}" for what, n in self._skipped.items())
            self.warnings.append(f"skipped what trmd does not read: {parts}")
        if self._incomplete:
            self.warnings.append(f"{self._incomplete} APS frame(s) do not read every pixel once "
                                 "(rolling shutter, a region of interest, or cut short) and "
                                 "were skipped: trmd reads whole global-shutter frames")
        missing = sum(f.exposure is None for f in self._frames)
        if missing:
            self.warnings.append(f"{missing} of {len(self._frames)} APS frames have no exposure "
                                 "(signal read not after reset read); they cannot be deblurred")

    # -- frames -------------------------------------------------------------------------------

    def frames(self) -> Iterator[Frame]:
        """APS frames in file order, assembled again from their samples (one in memory)."""
        if not self._frames:
            return
        asm = _ApsAssembler(self.width, self.height, keep_pixels=True)
        i = 0
        for k, a, t in self._records_from(0, None):
            samples = self._aps(a, t, k * AEDAT2_CHUNK_RECORDS, count=False)
            done = asm.feed(*samples) if samples is not None else []
            for _, exp, image in done:
                yield Frame(image, exp, i, f"{i:06d}")  # type: ignore[arg-type]
                i += 1
        for _, exp, image in asm.finish():
            yield Frame(image, exp, i, f"{i:06d}")  # type: ignore[arg-type]
            i += 1

    def frame_exposures(self) -> list[Exposure]:
        return [f.exposure for f in self._frames if f.exposure is not None]

    def num_frames(self) -> int:
        return len(self._frames)


def read_aedat2(path: Path, options: ReadOptions) -> Aedat2Recording:
    """Open a jAER AEDAT 2.0 file: DVS128 or DAVIS events, and DAVIS APS frames."""
    return Aedat2Recording(Path(path), options)


# -- AEDAT 3.1 --------------------------------------------------------------------------------


@dataclass
class _Frame3:
    """Where one AEDAT 3.1 frame is, and its exposure (no pixels)."""

    offset: int  # file offset of the frame event
    overflow: int
    size: tuple[int, int]
    position: tuple[int, int]
    channels: int
    exposure: Exposure | None
    color_filter: int = 0


@dataclass
class _Packets:
    """Counts of what the index pass met."""

    skipped: dict[str, int] = field(default_factory=dict)
    invalid: int = 0
    sources: dict[int, set[int]] = field(default_factory=dict)  # type → sources


class Aedat3Recording(ChunkedRecording):
    """An AEDAT 3.1 file (cAER / DV): polarity events (chunked by packets) and frame events."""

    def __init__(self, path: Path, options: ReadOptions) -> None:
        warnings: list[str] = []
        self.header = parse_aedat_header(path)
        if self.header.version != "3.1":
            raise FormatError(f"AEDAT {self.header.version} files are not supported", path=path,
                              hint="trmd reads AEDAT 2.0, 3.1 and 4.0: convert it with DV")
        fmt = self.header.value("Format")
        if fmt is not None and fmt.strip().upper() not in ("RAW", ""):
            raise FormatError(f"AEDAT 3.1 with '#Format: {fmt}' is not supported (only RAW)",
                              path=path, hint="re-export it uncompressed, or convert it with DV")
        _ignore_time_unit(options, warnings)
        self.path = Path(path)
        self._size = os.path.getsize(path)
        self._counts = _Packets()
        self._frames: list[_Frame3] = []
        self._pol_source, self._frame_source = self._scan_sources(path)
        size = self._sensor(options, warnings)
        super().__init__(path, "aedat3", size[0], size[1], warnings)
        self._build_index(self._first_pass())
        self._note()

    # -- packets ------------------------------------------------------------------------------

    def _packets(self, offset: int | None = None, *, want_data=lambda h: True
                 ) -> Iterator[tuple[int, np.void, bytes | None]]:
        """(offset, header, data or None) per packet from ``offset``; damage is a FormatError."""
        pos = self.header.data_offset if offset is None else offset
        with open(self.path, "rb") as fh:
            fh.seek(pos)
            k = 0
            while pos < self._size:
                raw = fh.read(28)
                if len(raw) < 28:
                    raise FormatError(f"the file ends inside the header of a packet at byte "
                                      f"{pos} (truncated?)", path=self.path,
                                      hint=self._truncate_hint(pos))
                h = np.frombuffer(raw, _AEDAT3_HEADER)[0]
                size, cap, num = int(h["size"]), int(h["capacity"]), int(h["number"])
                if size <= 0 or cap < 0 or num < 0 or num > cap or int(h["valid"]) > num \
                        or int(h["overflow"]) < 0:
                    raise FormatError(f"packet at byte {pos} has an impossible header "
                                      f"(eventSize {size}, capacity {cap}, number {num}): "
                                      "corrupt file", path=self.path, hint=_DAMAGED)
                length = size * cap
                if pos + 28 + length > self._size:
                    raise FormatError(f"the file ends inside a packet of {_name(h)} events at "
                                      f"byte {pos} (truncated?)", path=self.path,
                                      hint=self._truncate_hint(pos))
                if want_data(h):
                    data = fh.read(length)
                else:
                    fh.seek(length, os.SEEK_CUR)
                    data = None
                yield pos, h, data
                pos += 28 + length
                k += 1

    def _truncate_hint(self, pos: int) -> str:
        return ("if the recording was interrupted, keep its complete part: truncate -s "
                f"{pos} FILE (on a copy)")

    def _scan_sources(self, path: Path) -> tuple[int | None, int | None]:
        """The first source holding polarity events, and the first holding frames."""
        pol: set[int] = set()
        fr: set[int] = set()
        for _, h, _ in self._packets(want_data=lambda h: False):
            if int(h["type"]) == 1:
                pol.add(int(h["source"]))
            elif int(h["type"]) == 2:
                fr.add(int(h["source"]))
        self._counts.sources = {1: pol, 2: fr}
        return (min(pol) if pol else None), (min(fr) if fr else None)

    def _sensor(self, options: ReadOptions, warnings: list[str]) -> tuple[int | None, int | None]:
        wanted = self._pol_source if self._pol_source is not None else self._frame_source
        named = None
        for line in self.header.lines:
            m = re.match(r"\s*Source\s+(\d+)\s*:\s*(.*)", line)
            if m and (wanted is None or int(m[1]) == wanted):
                named = m[2].strip()
                break
        if named:
            key = named.lower().replace(" ", "")
            for fragment, size in _SOURCES:
                if fragment in key:
                    if options.sensor is not None and tuple(options.sensor) != size:
                        warnings.append(f"`sensor={tuple(options.sensor)}` ignored: the header "
                                        f"names a {named} ({size[0]}x{size[1]})")
                    return size
        if options.sensor is not None:
            return tuple(options.sensor)  # type: ignore[return-value]
        if options.frame_size is not None:
            return tuple(options.frame_size)  # type: ignore[return-value]
        return None, None

    def _polarity(self, h: np.void, data: bytes, count: bool) -> tuple[np.ndarray, ...]:
        if int(h["size"]) != 8:
            raise FormatError(f"a polarity packet has eventSize {int(h['size'])}, not 8 "
                              "(corrupt file?)", path=self.path, hint=_DAMAGED)
        ev = np.frombuffer(data, _POLARITY3, count=int(h["number"]))
        d = ev["data"]
        valid = (d & 1) != 0
        if count and not valid.all():
            self._counts.invalid += int((~valid).sum())
        d = d[valid]
        t32 = ev["t"][valid].astype(np.int64)
        if len(t32) and int(t32.min()) < 0:
            raise FormatError("a polarity event has a negative timestamp (corrupt file?)",
                              path=self.path, hint=_DAMAGED)
        t = (int(h["overflow"]) << 31) + t32
        x = (d >> 17).astype(np.uint16)
        y = ((d >> 2) & 0x7FFF).astype(np.uint16)
        p = np.where((d & 2) != 0, 1, -1).astype(np.int8)
        return x, y, t, p

    def _chunks(self, start_offset: int | None, first_ordinal: int, *, index: bool
                ) -> Iterator[Chunk]:
        parts: list[tuple[np.ndarray, ...]] = []
        n = 0
        k = first_ordinal
        resume: int | None = None

        def want(h) -> bool:
            typ = int(h["type"])
            return (typ == 1 and int(h["source"]) == self._pol_source) or (
                index and typ == 2 and int(h["source"]) == self._frame_source)

        def flush() -> Chunk:
            cols = [np.concatenate([q[i] for q in parts]) if len(parts) > 1 else parts[0][i]
                    for i in range(4)]
            return Chunk(k, cols[0], cols[1], cols[2], cols[3], resume)

        for pos, h, data in self._packets(start_offset, want_data=want):
            typ, src = int(h["type"]), int(h["source"])
            if typ == 1 and src == self._pol_source:
                assert data is not None
                if not parts:
                    resume = pos
                parts.append(self._polarity(h, data, index))
                n += len(parts[-1][0])
                if n >= AEDAT3_CHUNK_EVENTS:
                    yield flush()
                    parts, n, k = [], 0, k + 1
            elif index:
                if typ == 2 and src == self._frame_source:
                    assert data is not None
                    self._note_frames(pos, h, data)
                else:
                    name = f"{_name(h)} events (type {typ}" + (
                        f", source {src})" if typ in (1, 2) else ")")
                    self._counts.skipped[name] = self._counts.skipped.get(name, 0) + \
                        int(h["number"])
        if parts:
            yield flush()

    def _first_pass(self) -> Iterator[Chunk]:
        return self._chunks(None, 0, index=True)

    def _decode(self, start: int = 0, resume: Any = None) -> Iterator[Chunk]:
        if resume is not None:
            yield from self._chunks(int(resume), start, index=False)
            return
        for ch in self._chunks(None, 0, index=False):
            if ch.ordinal >= start:
                yield ch

    def _settle_size(self, xmax: int, ymax: int) -> None:
        if (self.width is None or self.height is None) and self._frames:
            f = self._frames[0]
            self.width = max(f.position[0] + f.size[0], xmax + 1)  # type: ignore[assignment]
            self.height = max(f.position[1] + f.size[1], ymax + 1)  # type: ignore[assignment]
            self.warnings.append(f"the header names no known sensor; using {self.width}x"
                                 f"{self.height} from the frames (pass `sensor=(W, H)` to set "
                                 "it)")
        super()._settle_size(xmax, ymax)

    # -- frames -------------------------------------------------------------------------------

    def _note_frames(self, pos: int, h: np.void, data: bytes) -> None:
        size, num = int(h["size"]), int(h["number"])
        if size < _FRAME3.itemsize:
            raise FormatError(f"a frame packet has eventSize {size}, less than a frame's "
                              f"{_FRAME3.itemsize}-byte header (corrupt file?)",
                              path=self.path, hint=_DAMAGED)
        overflow = int(h["overflow"]) << 31
        for i in range(num):
            meta = np.frombuffer(data, _FRAME3, count=1, offset=i * size)[0]
            info = int(meta["info"])
            if not info & 1:
                self._counts.invalid += 1
                continue
            channels = (info >> 1) & 7
            lx, ly = int(meta["length_x"]), int(meta["length_y"])
            if channels not in (1, 3, 4) or lx <= 0 or ly <= 0 or \
                    _FRAME3.itemsize + 2 * lx * ly * channels > size:
                raise FormatError(f"a frame at byte {pos + 28 + i * size} is {lx}x{ly} with "
                                  f"{channels} channel(s), which its eventSize {size} cannot "
                                  "hold (corrupt file?)", path=self.path, hint=_DAMAGED)
            t0, t1 = int(meta["start_exposure"]), int(meta["end_exposure"])
            exposure = Exposure(overflow + t0, overflow + t1) if t1 > t0 >= 0 else None
            self._frames.append(_Frame3(pos + 28 + i * size, int(h["overflow"]), (lx, ly),
                                        (int(meta["position_x"]), int(meta["position_y"])),
                                        channels, exposure, (info >> 4) & 0xF))

    def _note(self) -> None:
        c = self._counts
        if c.skipped:
            parts = ", ".join(f"{n} {what}" for what, n in c.skipped.items())
            self.warnings.append(f"skipped event types trmd does not read: {parts}")
        if c.invalid:
            self.warnings.append(f"{c.invalid} event(s) marked invalid by the recording "
                                 "software were skipped")
        for typ, what in ((1, "event"), (2, "frame")):
            if len(c.sources.get(typ, ())) > 1:
                srcs = sorted(c.sources[typ])
                self.warnings.append(f"the file has {what}s from {len(srcs)} sources "
                                     f"({', '.join(map(str, srcs))}); reading source {srcs[0]}")
        if not self._frames:
            return
        missing = sum(f.exposure is None for f in self._frames)
        if missing:
            self.warnings.append(f"{missing} of {len(self._frames)} frames have no exposure "
                                 "time; they cannot be deblurred")
        odd = [f for f in self._frames if f.size != (self.width, self.height)]
        if odd:
            f = odd[0]
            self.warnings.append(f"{len(odd)} frame(s) are {f.size[0]}x{f.size[1]} (offset "
                                 f"{f.position[0]},{f.position[1]}), not the "
                                 f"{self.width}x{self.height} sensor")
        mosaic = sum(f.color_filter != 0 and f.channels == 1 for f in self._frames)
        if mosaic:
            self.warnings.append(f"{mosaic} frame(s) are a raw colour mosaic (a Bayer filter): "
                                 "read as gray, not demosaiced")

    def frames(self) -> Iterator[Frame]:
        """Frame events in file order, decoded one at a time."""
        if not self._frames:
            return
        with open(self.path, "rb") as fh:
            for i, f in enumerate(self._frames):
                lx, ly = f.size
                fh.seek(f.offset + _FRAME3.itemsize)
                px = np.frombuffer(fh.read(2 * lx * ly * f.channels), "<u2")
                px = px.reshape(ly, lx) if f.channels == 1 else px.reshape(ly, lx, f.channels)
                order = {1: "gray", 3: "rgb", 4: "rgba"}[f.channels]
                yield Frame(pixels_to_float(px, order, max_value=65535), f.exposure, i,
                            f"{i:06d}")

    def frame_exposures(self) -> list[Exposure]:
        return [f.exposure for f in self._frames if f.exposure is not None]

    def num_frames(self) -> int:
        return len(self._frames)


def _name(h: np.void) -> str:
    return _TYPES.get(int(h["type"]), f"unknown-type-{int(h['type'])}")


def read_aedat3(path: Path, options: ReadOptions) -> Aedat3Recording:
    """Open an AEDAT 3.1 file: polarity events and frame events with their exposures."""
    return Aedat3Recording(Path(path), options)
