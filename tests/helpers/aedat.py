"""Reference writers for jAER AEDAT 2.0 and cAER AEDAT 3.1, built from the published format
descriptions (iniVation's "AEDAT 2.0" / "AEDAT 3.1" pages, jAER's address layouts, libcaer's
event structures) — independently of trmd's reader, which the tests check against them.

Events and frames are given in trmd's convention — x = column, y = row from the top, p = ±1,
t in µs — and encoded as the hardware and software write them.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: jAER AEChip class names used in the headers
DAVIS240 = "eu.seebetter.ini.chips.davis.DAVIS240C"
DAVIS346 = "eu.seebetter.ini.chips.davis.Davis346B"
DVS128 = "ch.unizh.ini.jaer.chip.retina.DVS128"


@dataclass(frozen=True)
class ApsFrame:
    """A DAVIS APS frame to encode: ``cds`` (H, W) ints 0..1023 = reset − signal read (row 0 at
    the top); reset reads from ``t_reset`` to ``exposure_start`` (the last one), signal reads
    from ``exposure_end`` (the first one) on, ``dt`` µs apart per column."""

    cds: np.ndarray
    t_reset: int
    exposure_start: int
    exposure_end: int


def aedat2_header(chip: str | None, extra: Sequence[str] = ()) -> bytes:
    lines = ["#!AER-DAT2.0", "# This is a raw AE data file - do not edit",
             "# Data format is int32 address, int32 timestamp (8 bytes total), repeated for each "
             "event", "# Timestamps tick is 1 us"]
    if chip:
        lines.append(f"# AEChip: {chip}")
    lines += list(extra)
    lines.append("#End Of ASCII Header")
    return "".join(line + "\r\n" for line in lines).encode()


def dvs128_addresses(x, y, p) -> np.ndarray:
    """jAER's DVS128: bit 0 = 0 for ON, x mirrored (127 − x) in bits 1–7, y counted from the
    bottom (127 − row) in bits 8–14."""
    x, y, p = (np.asarray(v, np.int64) for v in (x, y, p))
    return ((127 - y) << 8) | ((127 - x) << 1) | np.where(p > 0, 0, 1)


def davis_dvs_addresses(x, y, p, width: int, height: int) -> np.ndarray:
    """jAER's DAVIS DVS event: bit 31 clear, y from the bottom in bits 22–30, x mirrored
    (W − 1 − x) in bits 12–21, bit 11 set for ON."""
    x, y, p = (np.asarray(v, np.int64) for v in (x, y, p))
    return ((height - 1 - y) << 22) | ((width - 1 - x) << 12) | (np.where(p > 0, 1, 0) << 11)


def davis_aps_records(frame: ApsFrame, width: int, height: int, reset_value: int = 1023
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(addresses, timestamps) of one global-shutter frame: every pixel's reset read (readout
    type 0), then every pixel's signal read (type 1), read from the raw address (W−1, H−1) down
    to (0, 0) as jAER expects; APS x is not mirrored, y counts from the bottom."""
    rows, cols = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    raw_x, raw_y = cols.ravel(), (height - 1 - rows).ravel()
    order = np.lexsort((-raw_y, -raw_x))  # x descending, then y descending
    raw_x, raw_y = raw_x[order], raw_y[order]
    cds = np.asarray(frame.cds, np.int64)[height - 1 - raw_y, raw_x]
    base = (1 << 31) | (raw_y << 22) | (raw_x << 12)
    n = width * height
    reset = base | (0 << 10) | reset_value
    signal = base | (1 << 10) | (reset_value - cds)
    col = np.repeat(np.arange(width), height)[:n]
    span_r = max(frame.exposure_start - frame.t_reset, 0)
    t_r = frame.t_reset + (col * span_r) // max(width - 1, 1)
    t_r[-1] = frame.exposure_start
    t_s = frame.exposure_end + col * 3
    return np.concatenate([reset, signal]), np.concatenate([t_r, t_s])


def aedat2_bytes(addresses, timestamps, chip: str | None = DAVIS240,
                 extra_header: Sequence[str] = ()) -> bytes:
    """Header and big-endian (int32 address, int32 timestamp) records, sorted by time."""
    a = np.asarray(addresses, np.int64) & 0xFFFFFFFF
    t = np.asarray(timestamps, np.int64)
    order = np.argsort(t, kind="stable")
    rec = np.empty(len(a), [("a", ">u4"), ("t", ">u4")])
    rec["a"], rec["t"] = a[order], t[order] & 0xFFFFFFFF
    return aedat2_header(chip, extra_header) + rec.tobytes()


# -- AEDAT 3.1 ----------------------------------------------------------------------------------


def aedat3_header(source: str = "DAVIS240C", extra: Sequence[str] = ()) -> bytes:
    lines = ["#!AER-DAT3.1", "#Format: RAW", f"#Source 1: {source}",
             "#Start-Time: 2024-01-01 12:00:00 (TZ+0000)", *extra, "#!END-HEADER"]
    return "".join(line + "\r\n" for line in lines).encode()


def packet_header(event_type: int, source: int, size: int, ts_offset: int, overflow: int,
                  capacity: int, number: int, valid: int) -> bytes:
    return struct.pack("<hhiiiiii", event_type, source, size, ts_offset, overflow, capacity,
                       number, valid)


def polarity_packet(x, y, t, p, source: int = 1, valid=None) -> bytes:
    """One polarity packet (type 1): uint32 data = x << 17 | y << 2 | polarity << 1 | valid,
    int32 timestamp = the low 31 bits; all events must share one overflow (t >> 31)."""
    x, y, t, p = (np.asarray(v, np.int64) for v in (x, y, t, p))
    overflow = int(t[0]) >> 31
    assert (t >> 31 == overflow).all()
    ok = np.ones(len(t), bool) if valid is None else np.asarray(valid, bool)
    data = (x << 17) | (y << 2) | (np.where(p > 0, 1, 0) << 1) | ok.astype(np.int64)
    ev = np.empty(len(t), [("d", "<u4"), ("t", "<i4")])
    ev["d"], ev["t"] = data, t & 0x7FFFFFFF
    return packet_header(1, source, 8, 4, overflow, len(t), len(t), int(ok.sum())) + ev.tobytes()


def frame_packet(pixels: np.ndarray, exposure: tuple[int, int], frame: tuple[int, int] | None
                 = None, source: int = 1, position: tuple[int, int] = (0, 0),
                 valid: bool = True) -> bytes:
    """One frame packet (type 2) holding one frame: uint32 info (valid | channels << 1), int32
    start/end of frame, start/end of exposure, lengthX, lengthY, positionX, positionY, then
    uint16 pixels row by row (channels interleaved)."""
    px = np.asarray(pixels, np.uint16)
    h, w = px.shape[:2]
    ch = 1 if px.ndim == 2 else px.shape[2]
    f0, f1 = frame if frame is not None else (exposure[0] - 100, exposure[1] + 100)
    overflow = exposure[0] >> 31
    info = (1 if valid else 0) | (ch << 1)
    body = struct.pack("<Iiiiiiiii", info, f0 & 0x7FFFFFFF, f1 & 0x7FFFFFFF,
                       exposure[0] & 0x7FFFFFFF, exposure[1] & 0x7FFFFFFF, w, h, *position)
    body += px.astype("<u2").tobytes()
    return packet_header(2, source, len(body), 12, overflow, 1, 1, 1 if valid else 0) + body


def imu6_packet(t: int, n: int = 2, source: int = 1) -> bytes:
    """An IMU6 packet (type 3, 36-byte events) that readers of events and frames skip."""
    ev = b"".join(struct.pack("<Ii7f", 1, (t + i) & 0x7FFFFFFF, *([0.0] * 7)) for i in range(n))
    return packet_header(3, source, 36, 4, t >> 31, n, n, n) + ev
