"""Pictures people would rather see than read: voxel previews and labelled strips.

All functions return uint8 RGB arrays (H, W, 3); writing is :mod:`trmd_cli.write`'s job.
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
          gap: int = 4) -> np.ndarray:
    """Side-by-side strip of same-size images ([0, 1] float or uint8 RGB), optionally labelled."""
    tiles = [im if im.dtype == np.uint8 and im.ndim == 3 else to_rgb8(im) for im in images]
    if labels:
        tiles = [_label(t, s) for t, s in zip(tiles, labels)]
    h = max(t.shape[0] for t in tiles)
    sep = np.full((h, gap, 3), 255, np.uint8)
    out = []
    for i, t in enumerate(tiles):
        if t.shape[0] < h:
            t = np.pad(t, ((0, h - t.shape[0]), (0, 0), (0, 0)))
        out += ([sep] if i else []) + [t]
    return np.concatenate(out, axis=1)


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
