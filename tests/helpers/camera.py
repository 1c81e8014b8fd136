"""Small valid event files of every format, written byte by byte (the bad-input tests damage
them)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from trmd_cli.events import Exposure, make_stream
from trmd_cli.write import write_events_npz, write_events_text, write_h5

W, H = 64, 48


def stream(n: int = 3000, seed: int = 7):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(1_000, 2_000_000, n))
    return make_stream(rng.integers(0, W, n), rng.integers(0, H, n), t, rng.integers(0, 2, n),
                       W, H)


def evt2_bytes(t, x, y, p, header: bytes = b"% evt 2.0\n% geometry 64x48\n") -> bytes:
    """EVT 2.0: a TIME_HIGH word (0x8, time bits 33..6) when they change, then CD words
    (0x0 OFF / 0x1 ON, time bits 5..0 at 27..22, x at 21..11, y at 10..0)."""
    words, high = [], None
    for ti, xi, yi, pi in zip(t, x, y, p, strict=True):
        if ti >> 6 != high:
            high = ti >> 6
            words.append((0x8 << 28) | (high & 0x0FFFFFFF))
        words.append((int(pi > 0) << 28) | ((ti & 0x3F) << 22) | (int(xi) << 11) | int(yi))
    return header + np.array(words, "<u4").tobytes()


def dat_bytes(t, x, y, p, ev_size: int = 8) -> bytes:
    """Prophesee .dat: '%' header, event type 0x0C and size, then (uint32 t, x | y<<14 | p<<28)."""
    rec = np.empty(len(t), [("t", "<u4"), ("d", "<u4")])
    rec["t"] = t
    rec["d"] = np.asarray(x) | (np.asarray(y) << 14) | ((np.asarray(p) > 0).astype(int) << 28)
    head = f"% Date 2024-01-01 00:00:00\n% Width {W}\n% Height {H}\n".encode()
    return head + bytes([0x0C, ev_size]) + rec.tobytes()


def good(tmp: Path, fmt: str) -> Path:
    """A valid file of ``fmt`` in ``tmp`` (the starting point for cuts and flips)."""
    s = stream()
    path = tmp / f"good.{fmt}"
    if fmt == "txt":
        write_events_text(path, s)
    elif fmt == "npz":
        write_events_npz(path, s, [Exposure(1_000, 500_000)])
    elif fmt == "npy":
        np.save(path, np.stack([s.t / 1e6, s.x, s.y, s.p > 0], 1))
    elif fmt == "h5":
        write_h5(path, s)
    elif fmt == "raw":
        path.write_bytes(evt2_bytes(s.t, s.x, s.y, s.p))
    elif fmt == "dat":
        path.write_bytes(dat_bytes(s.t, s.x, s.y, s.p))
    elif fmt == "mat":
        import scipy.io as sio

        sio.savemat(path, {"t": s.t / 1e6, "x": s.x.astype(float), "y": s.y.astype(float),
                           "p": (s.p > 0).astype(float)})
    return path
