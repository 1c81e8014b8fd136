"""Videos of latent frames: MP4 (H.264 through imageio-ffmpeg) or animated GIF (Pillow).

Frames are appended one at a time; the file appears only when :meth:`VideoWriter.close`
succeeds (written under a temporary name beside the target, then renamed — see
:func:`trmd_cli.write.atomic_path`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import InputError
from .write import atomic_path, to_uint

__all__ = ["VideoWriter", "VIDEO_SUFFIXES", "check_video_path"]

#: output suffixes understood by :class:`VideoWriter`
VIDEO_SUFFIXES = (".mp4", ".gif")


def check_video_path(path: str | Path) -> Path:
    """Raise :class:`InputError` unless ``path`` ends in .mp4 or .gif."""
    path = Path(path)
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise InputError(f"video output must end in .mp4 or .gif, got {path.suffix or 'none'}",
                         path=path, hint="name it like slowmo.mp4 or slowmo.gif")
    return path


class VideoWriter:
    """Append float [0, 1] frames ((H, W) gray or (H, W, 3) RGB) to an MP4 or GIF.

    MP4 is streamed to ffmpeg (bounded memory); GIF frames are kept (as uint8) until close,
    because a GIF's palette and timing are written at the end. Odd sizes are padded by one
    edge row/column for H.264 (yuv420p needs even sizes). Values outside [0, 1] are clipped.

    Usage::

        with VideoWriter("slowmo.mp4", fps=30) as vw:
            for frame in frames:
                vw.append(frame)
    """

    def __init__(self, path: str | Path, fps: float = 30.0, quality: int = 8) -> None:
        self.path = check_video_path(path)
        if not (np.isfinite(fps) and fps > 0):
            raise InputError(f"`fps` must be positive, got {fps}", hint="e.g. `fps=30`")
        self.fps = float(fps)
        self.quality = int(quality)
        self.kind = self.path.suffix.lower()[1:]
        self.count = 0
        self._shape: tuple[int, ...] | None = None
        self._ctx = atomic_path(self.path)
        self._tmp = self._ctx.__enter__()
        self._gif: list[np.ndarray] = []
        self._plugin = None
        self._writer = None

    def append(self, frame: np.ndarray) -> None:
        img = to_uint(np.asarray(frame, np.float32), 8)
        if img.ndim == 3 and img.shape[2] == 1:
            img = img[..., 0]
        if self._shape is None:
            self._shape = img.shape
        elif img.shape != self._shape:
            raise InputError(f"video frame {self.count} has shape {img.shape}, the first had "
                             f"{self._shape}")
        if self.kind == "gif":
            self._gif.append(img)
        else:
            self._mp4_writer().append_data(_even(img))
        self.count += 1

    def _mp4_writer(self):
        if self._writer is None:
            import imageio.v3 as iio

            self._plugin = iio.imopen(self._tmp, "w", plugin="FFMPEG", extension=".mp4")
            self._writer = self._plugin.legacy_get_writer(
                fps=self.fps, codec="libx264", quality=self.quality, macro_block_size=1,
                ffmpeg_log_level="error", pixelformat="yuv420p")
        return self._writer

    def close(self) -> Path:
        """Finish the file and move it into place. Raises InputError for an empty video."""
        try:
            if self.count == 0:
                raise InputError("no frames to write", path=self.path)
            if self.kind == "gif":
                # GIF timing is in whole centiseconds; Pillow takes milliseconds per frame
                _write_gif(self._tmp, np.stack(self._gif), max(20, int(round(1000 / self.fps))))
                self._gif = []
            else:
                self._writer.close()
                self._plugin.close()
                self._writer = self._plugin = None
            if self._tmp.stat().st_size == 0:
                raise InputError("the video encoder wrote nothing", path=self.path,
                                 hint="check that imageio-ffmpeg is installed")
        except BaseException as e:
            self.abort(e)
            raise
        self._ctx.__exit__(None, None, None)
        return self.path

    def abort(self, exc: BaseException | None = None) -> None:
        """Drop the temporary file; the target is left untouched."""
        try:
            if self._writer is not None:
                self._writer.close()
                self._plugin.close()
        except Exception:  # noqa: BLE001 - already failing; the temp file is removed below
            pass
        self._writer = self._plugin = None
        exc = exc or RuntimeError("aborted")
        try:
            self._ctx.__exit__(type(exc), exc, None)
        except BaseException:  # noqa: BLE001 - atomic_path re-raises what it was given
            pass

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort(exc)


#: the palette of gray GIFs: every level, so gray frames are stored exactly
_GRAY_PALETTE = bytes(v for level in range(256) for v in (level, level, level))


def _write_gif(path: Path, frames: np.ndarray, duration_ms: int) -> None:
    """An animated GIF of uint8 frames, looping. Gray frames share one global palette of the
    256 gray levels: without it Pillow gives every frame after the first a palette of its own,
    which some readers (imageio with older Pillow: "No packer found from P to L") cannot
    convert back to gray; with it every frame reads back as gray, exactly."""
    if frames.ndim == 3:
        from PIL import Image

        images = [Image.fromarray(f, "L") for f in frames]
        images[0].save(path, format="GIF", save_all=True, append_images=images[1:],
                       duration=duration_ms, loop=0, palette=_GRAY_PALETTE, optimize=False)
        return
    import imageio.v3 as iio

    iio.imwrite(path, frames, extension=".gif", plugin="pillow", duration=duration_ms, loop=0)


def _even(img: np.ndarray) -> np.ndarray:
    h, w = img.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return img
    pad = [(0, h % 2), (0, w % 2)] + ([(0, 0)] if img.ndim == 3 else [])
    return np.pad(img, pad, mode="edge")
