"""Videos of latent frames: MP4 (H.264 through imageio-ffmpeg) or animated GIF (Pillow).

Frames are appended one at a time; the file appears only when :meth:`VideoWriter.close`
succeeds (written under a temporary name beside the target, then renamed — see
:func:`trmd_cli.write.atomic_path`).
"""

from __future__ import annotations

import errno
import io
import os
import re
import struct
import subprocess
import tempfile
from fractions import Fraction
from pathlib import Path

import numpy as np

from .errors import InputError, WriteError
from .write import atomic_path, open_output, to_uint, write_failure

__all__ = ["VideoWriter", "VIDEO_SUFFIXES", "check_video_path"]

#: output suffixes understood by :class:`VideoWriter`
VIDEO_SUFFIXES = (".mp4", ".gif")


#: frames per second a GIF can play: its frames last whole hundredths of a second, and
#: players show those under 20 ms for 100 ms
MAX_GIF_FPS = 50.0
#: frames per second an MP4 is written at, at most (players drop frames far below it)
MAX_MP4_FPS = 1000.0


def check_fps(path: str | Path, fps: float) -> float:
    """``fps``, refused unless a video at ``path`` (.mp4 or .gif) can play at it."""
    kind = Path(path).suffix.lower()
    top = MAX_GIF_FPS if kind == ".gif" else MAX_MP4_FPS
    if not (np.isfinite(fps) and 0 < fps <= top):
        raise InputError(f"`fps` must be a positive number up to {top:g} for a "
                         f"{kind or 'video'} file, got {fps:g}",
                         hint="e.g. `fps=30`" + (" (or write an .mp4)" if kind == ".gif" else ""))
    return float(fps)


def played_fps(path: str | Path, fps: float) -> float:
    """The rate a video at ``path`` written at ``fps`` plays at: a GIF's frames last whole
    hundredths of a second (30 fps → 3 hundredths: 33.3 fps); an MP4's rate is ``fps``."""
    if Path(path).suffix.lower() != ".gif":
        return float(fps)
    return 100.0 / _gif_hundredths(fps)


def _gif_hundredths(fps: float) -> int:
    return max(2, int(round(100.0 / float(fps))))


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
        self.fps = check_fps(self.path, fps)
        self.quality = int(quality)
        self.kind = self.path.suffix.lower()[1:]
        self.count = 0
        self._shape: tuple[int, ...] | None = None
        self._ctx = atomic_path(self.path)
        self._tmp = self._ctx.__enter__()
        self._gif: list[np.ndarray] = []
        self._encoder: _Encoder | None = None

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
            try:
                if self._encoder is None:
                    self._encoder = _Encoder(self._tmp, _even(img).shape, self.fps,
                                             self.quality)
                self._encoder.write(_even(img))
            except BaseException as e:
                raise self._failed(e) from None
        self.count += 1

    def close(self) -> Path:
        """Finish the file, check that it is whole, and move it into place.

        Raises:
            InputError: no frames. WriteError: the disk is full, the folder is read-only, or
            the encoder did not finish the file (the video is then not there: a player could
            not open it).
        """
        try:
            if self.count == 0:
                raise InputError("no frames to write", path=self.path)
            if self.kind == "gif":
                # GIF timing is in whole hundredths of a second (see :func:`played_fps`);
                # Pillow takes milliseconds per frame, and rounds them down to hundredths
                buffer = io.BytesIO()
                _write_gif(buffer, np.stack(self._gif), 10 * _gif_hundredths(self.fps))
                self._gif = []
                with open_output(self._tmp) as fh:
                    fh.write(buffer.getbuffer())
            else:
                encoder, self._encoder = self._encoder, None
                encoder.finish(self.path)
            if self._tmp.stat().st_size == 0:
                raise WriteError("the video encoder wrote nothing", path=self.path,
                                 hint="check that imageio-ffmpeg is installed")
        except BaseException as e:
            raise self._failed(e) from None
        self._ctx.__exit__(None, None, None)
        return self.path

    def _failed(self, e: BaseException) -> BaseException:
        """Abort, and say ``e`` as one line when it is a failure to write."""
        self.abort(e)
        return write_failure(e, self.path.parent, self._tmp) or e

    def abort(self, exc: BaseException | None = None) -> None:
        """Drop the temporary file (stopping the encoder); the target is left untouched."""
        if self._encoder is not None:
            self._encoder.kill()
            self._encoder = None
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


class _Encoder:
    """FFmpeg (the one imageio-ffmpeg ships) turning raw frames from a pipe into H.264 in an MP4,
    with the settings imageio's FFmpeg writer used: libx264, yuv420p, constant quality.

    Its messages go to a temporary file, not the terminal: they become the one error line when
    encoding fails. It runs in a process group of its own (Ctrl-C at the terminal reaches only
    trmd, which then stops it: :meth:`kill`).
    """

    def __init__(self, path: Path, shape: tuple[int, ...], fps: float, quality: int) -> None:
        import imageio_ffmpeg

        h, w = shape[:2]
        crf = int((1 - quality / 10.0) * 51)
        self.cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-f", "rawvideo", "-vcodec",
                    "rawvideo", "-s", f"{w}x{h}", "-pix_fmt", "gray" if len(shape) == 2 else
                    "rgb24", "-r", str(Fraction(fps).limit_denominator()), "-i", "-", "-an",
                    "-vcodec", "libx264", "-pix_fmt", "yuv420p", "-crf", str(crf), "-v",
                    "error", str(path)]
        self._log = tempfile.TemporaryFile()
        try:
            self._proc = subprocess.Popen(self.cmd, stdin=subprocess.PIPE,
                                          stdout=subprocess.DEVNULL, stderr=self._log,
                                          start_new_session=True)
        except BaseException:
            self._log.close()
            raise

    def write(self, frame: np.ndarray) -> None:
        try:
            self._proc.stdin.write(np.ascontiguousarray(frame).data)
        except BrokenPipeError:  # FFmpeg stopped: say why
            self._fail(None)

    def finish(self, target: Path) -> None:
        """Close the pipe, wait for FFmpeg, and check the file it wrote is a whole MP4."""
        try:
            self._proc.stdin.close()
        except BrokenPipeError:
            pass
        code = self._proc.wait()
        if code != 0:
            self._fail(code)
        problem = mp4_problem(Path(self.cmd[-1]))
        if problem is not None:
            self._fail(code, problem)
        self._log.close()

    def _fail(self, code: int | None, problem: str | None = None) -> None:
        self._log.seek(0)
        lines = [ln.strip() for ln in self._log.read().decode("utf-8", "replace").splitlines()
                 if ln.strip()]
        self.kill()
        said = re.sub(r"^\[[^\]]*\]\s*", "", lines[-1]) if lines else ""
        for err in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES):
            if os.strerror(err) in said:
                raise OSError(err, os.strerror(err))
        if not said and self._disk_full():
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        what = problem or (f"FFmpeg stopped with exit code {code}" if code else "FFmpeg stopped")
        raise WriteError(f"the video encoder did not finish the file: {what}"
                         + (f" ({said})" if said else ""), path=Path(self.cmd[-1]).parent,
                         hint="nothing was written; check the free space and run again")

    def _disk_full(self) -> bool:
        try:
            st = os.statvfs(Path(self.cmd[-1]).parent)
        except OSError:
            return False
        return st.f_bavail * st.f_frsize < (1 << 20)

    def kill(self) -> None:
        """Stop FFmpeg now (an aborted video): it must not outlive the run."""
        if self._proc.poll() is None:
            self._proc.kill()
        try:
            self._proc.stdin.close()
        except (OSError, ValueError):
            pass
        self._proc.wait()
        if not self._log.closed:
            self._log.close()


def mp4_problem(path: str | Path) -> str | None:
    """What keeps ``path`` from being a whole MP4, or None: its top-level boxes must tile the
    file exactly and include ``moov`` (the index, written last: a file cut short lacks it) and
    ``mdat`` (the frames)."""
    size = os.path.getsize(path)
    seen: set[bytes] = set()
    pos = 0
    with open(path, "rb") as fh:
        while pos < size:
            fh.seek(pos)
            head = fh.read(16)
            if len(head) < 8:
                return f"it ends inside a box header at byte {pos}"
            length, kind = struct.unpack(">I4s", head[:8])
            if length == 1:
                if len(head) < 16:
                    return f"it ends inside a box header at byte {pos}"
                (length,) = struct.unpack(">Q", head[8:16])
            elif length == 0:
                length = size - pos
            if length < 8 or pos + length > size:
                return (f"its {kind.decode('latin-1')!r} box at byte {pos} runs past the end "
                        f"of the {size}-byte file")
            seen.add(kind)
            pos += length
    if b"moov" not in seen:
        return "it has no 'moov' box (the index FFmpeg writes last)"
    if b"mdat" not in seen:
        return "it has no 'mdat' box (the frames)"
    return None


def _even(img: np.ndarray) -> np.ndarray:
    h, w = img.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return img
    pad = [(0, h % 2), (0, w % 2)] + ([(0, 0)] if img.ndim == 3 else [])
    return np.pad(img, pad, mode="edge")
