"""Intensity frames: images on disk → float32 [0, 1]."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError

__all__ = ["read_image", "read_image_noted", "clip_note", "IMAGE_EXTENSIONS"]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm")


def clip_note(image: np.ndarray, name: str) -> str | None:
    """What clipping ``image`` to [0, 1] would change, as a warning, or None when nothing
    (beyond float rounding) lies outside: intensities cannot be negative or above white."""
    img = np.asarray(image)
    if img.dtype.kind != "f" or not img.size:
        return None
    lo, hi = float(img.min()), float(img.max())
    if lo >= -1e-6 and hi <= 1 + 1e-6:
        return None
    out = float(np.count_nonzero((img < 0) | (img > 1))) / img.size
    return (f"frame {name}: {100 * out:.3g} % of its pixel values lie outside [0, 1] (from "
            f"{lo:.4g} to {hi:.4g}) and were clipped — a frame holds intensities in [0, 1]: "
            "check how it was stored")


def read_image(path: str | Path) -> np.ndarray:
    """Read an 8/16-bit gray or colour image as float32 in [0, 1] (see
    :func:`read_image_noted`, which also says what clipping changed)."""
    return read_image_noted(path)[0]


def read_image_noted(path: str | Path) -> tuple[np.ndarray, str | None]:
    """Read an 8/16-bit gray or colour image as float32 in [0, 1], and the warning about the
    values a float image held outside [0, 1] (clipped), if any.

    Returns:
        (H, W) for gray, (H, W, 3) RGB for colour (alpha dropped). Gray stored as 3 equal
        channels comes back as (H, W).
    Raises:
        InputError: missing file; a float image holding NaN or infinite values (either: a
            pixel that is not an intensity). FormatError: not a readable image.
    """
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError("image not found", path=path, hint="check the path")
    import contextlib
    import threading

    from .aedat4 import _Capture, _native_stderr_captured

    data = np.fromfile(path, np.uint8)
    img = None
    # libpng prints its own complaint about a damaged PNG straight to fd 2 (OpenCV's log level
    # does not reach it), and OpenCV raises for headers claiming more than 2^30 pixels. fd 2 is
    # shared by all threads: only the main thread (the CLI's) may swap it.
    main = threading.current_thread() is threading.main_thread()
    with _native_stderr_captured() if main else contextlib.nullcontext(_Capture()) as capture:
        try:
            img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        except cv2.error:
            img = None
        capture.drop = img is None
    if img is None:
        raise FormatError("not a readable image (truncated or corrupt?)", path=path,
                          hint="use PNG, JPG or TIFF")
    if img.dtype == np.uint8:
        out = img.astype(np.float32) / 255.0
    elif img.dtype == np.uint16:
        out = img.astype(np.float32) / 65535.0
    elif img.dtype.kind == "f":
        out = img.astype(np.float32)
        bad = np.count_nonzero(~np.isfinite(out))
        if bad:
            raise InputError(f"{bad} pixel value(s) are NaN or infinite", path=path,
                             hint="repair or re-export the image: pixels are intensities in "
                                  "[0, 1]")
        note = clip_note(out, path.stem)
        out = np.clip(out, 0, 1)
    else:
        raise FormatError(f"unsupported pixel type {img.dtype}", path=path)
    if img.dtype.kind != "f":
        note = None
    if out.ndim == 3:
        if out.shape[2] == 4:
            out = out[..., :3]
        if out.shape[2] == 1:
            out = out[..., 0]
        else:
            out = out[..., ::-1]  # OpenCV BGR → RGB
            if (np.array_equal(out[..., 0], out[..., 1])
                    and np.array_equal(out[..., 1], out[..., 2])):
                out = out[..., 0]
    return np.ascontiguousarray(out), note


def check_frame_matches(image: np.ndarray, width: int, height: int, path) -> None:
    if image.shape[:2] != (height, width):
        raise InputError(
            f"image is {image.shape[1]}x{image.shape[0]} but the events' sensor is "
            f"{width}x{height}", path=path, hint="pass the matching frame, or `sensor=(W, H)`")
