"""The training curve as a PNG, drawn with OpenCV lines (no matplotlib).

Top panel: training loss against step (log scale). Bottom panel: validation PSNR (middle frame
and whole sequence) against step. Returned images are RGB uint8 (H, W, 3).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["draw_curve", "write_curve", "nice_ticks", "log_ticks", "COLORS"]

#: RGB colours of the series
COLORS = {"loss": (31, 119, 180), "val_psnr_mid": (214, 39, 40), "val_psnr_seq": (44, 160, 44)}
_AXIS = (60, 60, 60)
_GRID = (225, 225, 225)
_FONT = 0  # cv2.FONT_HERSHEY_SIMPLEX


def nice_ticks(lo: float, hi: float, count: int = 5) -> list[float]:
    """Round tick values covering [lo, hi] (steps of 1, 2 or 5 × 10^k)."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return []
    if hi <= lo:
        return [lo]
    raw = (hi - lo) / max(count, 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw)
    start = math.ceil(lo / step - 1e-9) * step
    ticks = []
    t = start
    while t <= hi + 1e-9 * step:
        ticks.append(round(t, 12))
        t += step
    return ticks


def log_ticks(lo: float, hi: float) -> list[float]:
    """Tick values for a log axis over [lo, hi] (> 0): 1, 2, 5 × 10^k, thinned to 1 × 10^k
    over wide ranges, plain linear ticks over very narrow ones."""
    if not (lo > 0 and hi > lo):
        return [lo] if lo > 0 else []
    e0, e1 = math.floor(math.log10(lo)) - 1, math.ceil(math.log10(hi)) + 1
    cands = [m * 10.0 ** e for e in range(e0, e1 + 1) for m in (1, 2, 5)]
    inside = [v for v in cands if lo <= v <= hi]
    if len(inside) > 8:
        inside = [v for v in inside if f"{v:e}".startswith("1")]
    if len(inside) < 2:
        inside = [v for v in nice_ticks(lo, hi, 4) if v > 0]
    return inside


def _fmt(v: float) -> str:
    if v == 0:
        return "0"
    # step axes: 15k, 20k, 25k (1 significant digit in e-notation would print all three as 2e4)
    if abs(v) >= 1e6:
        return f"{v / 1e6:.4g}M"
    if abs(v) >= 1e4:
        return f"{v / 1e3:.4g}k"
    if abs(v) < 1e-2:
        return f"{v:.0e}".replace("e+0", "e").replace("e-0", "e-")
    return f"{v:g}"


def _panel(img: np.ndarray, rect: tuple[int, int, int, int],
           series: Sequence[tuple[np.ndarray, np.ndarray, tuple[int, int, int], str]],
           *, log_y: bool, title: str, x_range: tuple[float, float]) -> None:
    import cv2

    x0, y0, x1, y1 = rect
    cv2.putText(img, title, (x0, y0 - 8), _FONT, 0.5, _AXIS, 1, cv2.LINE_AA)
    cv2.rectangle(img, (x0, y0), (x1, y1), _AXIS, 1)
    pts = [(xs, (np.log10(np.maximum(ys, 1e-12)) if log_y else ys), c, lab)
           for xs, ys, c, lab in series if len(xs)]
    if not pts:
        cv2.putText(img, "no data yet", (x0 + 10, (y0 + y1) // 2), _FONT, 0.5, _AXIS, 1,
                    cv2.LINE_AA)
        return
    ally = np.concatenate([p[1] for p in pts])
    lo, hi = float(ally.min()), float(ally.max())
    pad = 0.05 * (hi - lo) if hi > lo else (0.5 if log_y else max(abs(hi) * 0.05, 0.5))
    lo, hi = lo - pad, hi + pad
    xa, xb = x_range

    def px(x: np.ndarray) -> np.ndarray:
        return x0 + (np.asarray(x, float) - xa) / max(xb - xa, 1e-12) * (x1 - x0)

    def py(y: np.ndarray) -> np.ndarray:
        return y1 - (np.asarray(y, float) - lo) / (hi - lo) * (y1 - y0)

    for t in nice_ticks(xa, xb, 6):
        x = int(round(float(px(t))))
        cv2.line(img, (x, y0 + 1), (x, y1 - 1), _GRID, 1)
        cv2.putText(img, _fmt(t), (x - 12, y1 + 16), _FONT, 0.4, _AXIS, 1, cv2.LINE_AA)
    if log_y:
        values = log_ticks(10 ** lo, 10 ** hi)
        ticks = [math.log10(v) for v in values]
        labels = [_fmt(v) for v in values]
    else:
        ticks = nice_ticks(lo, hi, 5)
        labels = [_fmt(t) for t in ticks]
    for t, lab in zip(ticks, labels, strict=True):
        y = int(round(float(py(t))))
        cv2.line(img, (x0 + 1, y), (x1 - 1, y), _GRID, 1)
        cv2.putText(img, lab, (x0 - 52, y + 4), _FONT, 0.4, _AXIS, 1, cv2.LINE_AA)
    cv2.rectangle(img, (x0, y0), (x1, y1), _AXIS, 1)
    for i, (xs, ys, colour, label) in enumerate(pts):
        p = np.stack([px(xs), py(ys)], 1).round().astype(np.int32)
        if len(p) == 1:
            cv2.circle(img, tuple(int(v) for v in p[0]), 3, colour, -1, cv2.LINE_AA)
        else:
            cv2.polylines(img, [p.reshape(-1, 1, 2)], False, colour, 2, cv2.LINE_AA)
        # legend on the title line, right-aligned, so it never hides the data
        lx = x1 - 190 * (len(pts) - i)
        cv2.line(img, (lx, y0 - 12), (lx + 22, y0 - 12), colour, 2)
        cv2.putText(img, label, (lx + 28, y0 - 8), _FONT, 0.45, _AXIS, 1, cv2.LINE_AA)


def _column(history: Sequence[dict], key: str) -> tuple[np.ndarray, np.ndarray]:
    rows = [(r["step"], r[key]) for r in history
            if r.get(key) is not None and math.isfinite(float(r[key]))]
    if not rows:
        return np.zeros(0), np.zeros(0)
    a = np.asarray(rows, float)
    return a[:, 0], a[:, 1]


def draw_curve(history: Sequence[dict], *, title: str = "", width: int = 900,
               height: int = 640) -> np.ndarray:
    """Training curve image from log rows (dicts with ``step``, ``loss``, ``val_psnr_mid``,
    ``val_psnr_seq``; missing or None values are skipped). Returns RGB uint8 (H, W, 3)."""
    img = np.full((height, width, 3), 255, np.uint8)
    steps = [r["step"] for r in history]
    x_range = (0.0, float(max(steps))) if steps and max(steps) > 0 else (0.0, 1.0)
    left, right, top, gap, bottom = 80, width - 20, 40, 70, height - 40
    mid = top + (bottom - top - gap) // 2
    loss = _column(history, "loss")
    _panel(img, (left, top, right, mid), [(*loss, COLORS["loss"], "train loss")],
           log_y=True, title=(f"{title}: " if title else "") + "training loss", x_range=x_range)
    _panel(img, (left, mid + gap, right, bottom),
           [(*_column(history, "val_psnr_mid"), COLORS["val_psnr_mid"], "val PSNR middle"),
            (*_column(history, "val_psnr_seq"), COLORS["val_psnr_seq"], "val PSNR sequence")],
           log_y=False, title="validation PSNR (dB)", x_range=x_range)
    import cv2

    cv2.putText(img, "step", (right - 30, height - 8), _FONT, 0.45, _AXIS, 1, cv2.LINE_AA)
    return img


def write_curve(path: str | Path, history: Sequence[dict], *, title: str = "") -> Path:
    """Draw :func:`draw_curve` and write it as PNG, atomically."""
    from ..write import write_image

    return write_image(path, draw_curve(history, title=title))
