"""Pictures people would rather see than read: voxel previews and labelled strips.

Functions return uint8 RGB arrays (H, W, 3) — or, for :func:`strip` with ``keep_float``, [0, 1]
float32 to be written at any bit depth; writing is :mod:`trmd_cli.write`'s job.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["voxel_preview", "strip", "to_rgb8"]


def to_rgb8(image: np.ndarray) -> np.ndarray:
    """[0, 1] float (H, W) or (H, W, 3) → uint8 RGB (values outside [0, 1] clipped)."""
    img = np.clip(np.nan_to_num(np.asarray(image, np.float32)), 0, 1)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return (img * 255 + 0.5).astype(np.uint8)


def _label(tile: np.ndarray, text: str) -> np.ndarray:
    import cv2

    tile = tile.copy()
    scale = max(0.35, min(tile.shape[:2]) / 400)
    thick = max(1, int(round(scale * 2)))
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
    cv2.rectangle(tile, (0, 0), (tw + 8, th + base + 8), (0, 0, 0), -1)
    cv2.putText(tile, text, (4, th + 4), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), thick,
                cv2.LINE_AA)
    return tile


def strip(images: Sequence[np.ndarray], labels: Sequence[str] | None = None,
          gap: int = 4, *, keep_float: bool = False) -> np.ndarray:
    """Side-by-side strip of images, optionally labelled; shorter ones are padded at the bottom.

    Args:
        images: [0, 1] float (H, W) or (H, W, 3), or uint8 RGB.
        labels: one per image, drawn at its top left corner.
        gap: width of the white separators, pixels.
        keep_float: return float32 [0, 1] — gray when every image is gray — so that the strip
            can be written at 16 bits, labels as light text on a dark outline; else uint8 RGB,
            each label in a black box.
    """
    if keep_float:
        tiles = [np.clip(im, 0, 1).astype(np.float32) for im in images]
        if any(t.ndim == 3 for t in tiles):
            tiles = [np.repeat(t[..., None], 3, axis=2) if t.ndim == 2 else t for t in tiles]
        out = _row(tiles, gap, 1.0)
        if labels:
            _outline_labels(out, labels, [t.shape[1] for t in tiles], gap)
        return out
    tiles = [im if im.dtype == np.uint8 and im.ndim == 3 else to_rgb8(im) for im in images]
    if labels:
        tiles = [_label(t, s) for t, s in zip(tiles, labels)]
    return _row(tiles, gap, 255)


def _row(tiles: Sequence[np.ndarray], gap: int, white: float) -> np.ndarray:
    """Tiles of one dtype and channel count side by side, white separators between them."""
    h = max(t.shape[0] for t in tiles)
    out = []
    for i, t in enumerate(tiles):
        if t.shape[0] < h:
            t = np.pad(t, ((0, h - t.shape[0]), *([(0, 0)] * (t.ndim - 1))))
        if i:
            out.append(np.full((h, gap, *t.shape[2:]), white, t.dtype))
        out.append(t)
    return np.concatenate(out, axis=1)


def _outline_labels(row: np.ndarray, labels: Sequence[str], widths: Sequence[int],
                    gap: int) -> None:
    """Write ``labels`` into a float strip in place, one at the top left of each tile."""
    import cv2

    scale = max(0.35, row.shape[0] / 600)
    y = int(18 * scale / 0.5)
    # OpenCV draws text on 8-bit images only: draw masks, then paint the float strip
    outline = np.zeros(row.shape[:2], np.uint8)
    text_mask = np.zeros(row.shape[:2], np.uint8)
    x = 0
    for text, w in zip(labels, widths, strict=True):
        cv2.putText(outline, text, (x + 4, y), cv2.FONT_HERSHEY_SIMPLEX, scale, 255, 3,
                    cv2.LINE_AA)
        cv2.putText(text_mask, text, (x + 4, y), cv2.FONT_HERSHEY_SIMPLEX, scale, 255, 1,
                    cv2.LINE_AA)
        x += w + gap
    # dark outline under light text: readable on any background
    row[outline > 127] = 0.0
    row[text_mask > 127] = 1.0


def voxel_preview(voxels: np.ndarray, labels: Sequence[str] | None = None) -> np.ndarray:
    """Red (positive) / blue (negative) strip of the voxel channels (C, H, W), one shared scale
    (the 99.5th percentile of |V|) so channels compare."""
    v = np.asarray(voxels, np.float32)
    scale = float(np.percentile(np.abs(v), 99.5)) if v.size else 1.0
    scale = scale if scale > 0 else 1.0
    tiles = []
    for ch in v:
        a = np.clip(ch / scale, -1, 1)
        rgb = np.full((*a.shape, 3), 1.0, np.float32)
        pos, neg = np.clip(a, 0, 1), np.clip(-a, 0, 1)
        rgb[..., 1] -= pos + neg
        rgb[..., 2] -= pos
        rgb[..., 0] -= neg
        tiles.append(to_rgb8(rgb))
    return strip(tiles, labels)
