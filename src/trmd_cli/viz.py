"""Pictures people would rather see than read: voxel previews and labelled strips.

Functions return uint8 RGB arrays (H, W, 3) — or, for :func:`strip` with ``keep_float``, [0, 1]
float32 to be written at any bit depth; writing is :mod:`trmd_cli.write`'s job.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["voxel_preview", "strip", "to_rgb8", "flow_colours", "colour_wheel", "flow_picture",
           "weight_picture", "event_picture"]


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


def flow_colours(dx: np.ndarray, dy: np.ndarray, scale_px: float) -> np.ndarray:
    """Displacements (pixels, +x right, +y down) as colours: the hue is the direction — 0° (red)
    to the right, then clockwise on screen through 90° down, 180° left, 270° up — and the
    saturation the length over ``scale_px`` (white = no motion, full colour from
    ``scale_px`` on). Returns uint8 RGB of the inputs' shape + (3,)."""
    import cv2

    dx = np.nan_to_num(np.asarray(dx, np.float32))
    dy = np.nan_to_num(np.asarray(dy, np.float32))
    angle = np.degrees(np.arctan2(dy, dx)) % 360.0
    sat = np.clip(np.hypot(dx, dy) / max(float(scale_px), 1e-6), 0.0, 1.0)
    hsv = np.stack([angle, sat, np.ones_like(sat)], axis=-1).astype(np.float32)
    # float HSV in OpenCV: hue in degrees [0, 360), saturation and value in [0, 1]
    rgb = cv2.cvtColor(hsv.reshape(-1, 1, 3), cv2.COLOR_HSV2RGB).reshape(hsv.shape)
    return (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)


def colour_wheel(size: int) -> np.ndarray:
    """The legend of :func:`flow_colours`: a disc of diameter ``size`` pixels whose every point
    has the colour of the displacement from the centre to it (the rim = the picture's scale),
    on a dark grey square. uint8 RGB (size, size, 3)."""
    r = (size - 1) / 2
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    ox, oy = xx - r, yy - r
    out = flow_colours(ox, oy, r)
    out[np.hypot(ox, oy) > r] = 40
    return out


def flow_picture(displacement: np.ndarray, scale_px: float | None = None,
                 legend: bool = True) -> np.ndarray:
    """A flow picture of (H, W, 2) displacements in pixels (see :func:`flow_colours`), with a
    colour-wheel legend in the bottom right corner labelled with its scale. ``scale_px``: the
    length shown at full colour (default: the largest displacement, at least 1 px).
    uint8 RGB (H, W, 3)."""
    import cv2

    d = np.asarray(displacement, np.float32)
    length = np.hypot(d[..., 0], d[..., 1])
    scale = max(float(length.max(initial=0.0)), 1.0) if scale_px is None else float(scale_px)
    out = flow_colours(d[..., 0], d[..., 1], scale)
    h, w = out.shape[:2]
    size = int(min(h, w) * 0.3)
    if not legend or size < 16:
        return out
    out = out.copy()
    pad = 4
    text = f"{scale:.1f} px"
    fs = max(0.3, size / 160)
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, fs, 1)
    box_w, box_h = max(size, tw) + 2 * pad, size + th + base + 3 * pad
    x0, y0 = w - box_w - pad, h - box_h - pad
    if x0 < 0 or y0 < 0:
        return out
    out[y0:y0 + box_h, x0:x0 + box_w] = 40
    wx = x0 + (box_w - size) // 2
    out[y0 + pad:y0 + pad + size, wx:wx + size] = colour_wheel(size)
    cv2.putText(out, text, (x0 + (box_w - tw) // 2, y0 + box_h - pad - base),
                cv2.FONT_HERSHEY_SIMPLEX, fs, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def weight_picture(weight: np.ndarray) -> np.ndarray:
    """The motion method's per-pixel weight (H, W) in [0, 1] as gray: white where the
    deconvolution is used, black where EDI is. uint8 RGB (H, W, 3)."""
    return to_rgb8(np.asarray(weight, np.float32))


def event_picture(votes: Sequence[np.ndarray], labels: Sequence[str] | None = None
                  ) -> np.ndarray:
    """Images of events (vote counts, (H, W) each) side by side on one shared scale (the 99.5th
    percentile of the counts of all of them, ignoring empty pixels), dark events on white so
    that sharper means crisper lines. uint8 RGB strip."""
    vs = [np.asarray(v, np.float32) for v in votes]
    nz = np.concatenate([v[v > 0] for v in vs]) if vs else np.zeros(0, np.float32)
    scale = float(np.percentile(nz, 99.5)) if nz.size else 1.0
    tiles = [1.0 - np.clip(v / max(scale, 1e-6), 0.0, 1.0) for v in vs]
    return strip(tiles, labels)
