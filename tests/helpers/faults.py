"""Failures of the disk, injected where the bytes of an output reach it.

trmd writes every output through ``os.pwrite`` (:class:`trmd_cli.write._OutputFile`), creates
its temporaries with ``os.open`` (``tempfile.mkstemp``) and ``os.mkdir`` (``mkdtemp``), and has
FFmpeg write videos. :func:`disk_full` and :func:`read_only` make those calls fail as a full disk
or a read-only mount would, for trmd's temporary names only (``.NAME.trmd-PID-…``), so nothing
else of the test process is disturbed. :func:`fake_ffmpeg` runs the real FFmpeg and then spoils
its result the way a full disk did (a 4,096-byte file and exit code 0, or an error and exit 1).
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

import pytest


def _ours(name: str | None) -> bool:
    """A temporary of trmd's, or a file inside one (a folder being assembled)."""
    return name is not None and ".trmd-" in name


def _fd_name(fd: int) -> str | None:
    try:
        return os.readlink(f"/proc/self/fd/{fd}")
    except OSError:
        return None


def disk_full(monkeypatch, after_bytes: int = 0, code: int = errno.ENOSPC) -> dict:
    """``os.pwrite`` / ``os.write`` into trmd's temporaries fail with ``code`` once
    ``after_bytes`` bytes went through them. Returns counters (``written``, ``failed``)."""
    if not Path("/proc/self/fd").is_dir():
        pytest.skip("needs /proc to tell which file a descriptor is")
    seen = {"written": 0, "failed": 0}
    real_pwrite, real_write = os.pwrite, os.write

    def check(fd: int, data) -> None:
        if not _ours(_fd_name(fd)):
            return
        size = memoryview(data).nbytes
        if seen["written"] + size > after_bytes:
            seen["failed"] += 1
            raise OSError(code, os.strerror(code))
        seen["written"] += size

    def pwrite(fd, data, offset):
        check(fd, data)
        return real_pwrite(fd, data, offset)

    def write(fd, data):
        check(fd, data)
        return real_write(fd, data)

    monkeypatch.setattr(os, "pwrite", pwrite)
    monkeypatch.setattr(os, "write", write)
    return seen


def read_only(monkeypatch, code: int = errno.EROFS) -> None:
    """Creating trmd's temporary files and folders fails as on a read-only mount."""
    real_open, real_mkdir = os.open, os.mkdir

    def opener(path, flags, mode=0o777, *, dir_fd=None):
        if flags & os.O_CREAT and _ours(os.fspath(path)):
            raise OSError(code, os.strerror(code), os.fspath(path))
        return real_open(path, flags, mode, dir_fd=dir_fd)

    def mkdir(path, mode=0o777, *, dir_fd=None):
        if _ours(os.fspath(path)):
            raise OSError(code, os.strerror(code), os.fspath(path))
        return real_mkdir(path, mode, dir_fd=dir_fd)

    monkeypatch.setattr(os, "open", opener)
    monkeypatch.setattr(os, "mkdir", mkdir)


def fake_ffmpeg(monkeypatch, tmp_path: Path, how: str) -> Path:
    """Put an FFmpeg in front of the real one: ``how="cut"`` lets it finish and then cuts its
    file to 4,096 bytes and exits 0 (what FFmpeg did on a full disk); ``how="enospc"`` prints
    FFmpeg's own complaint about a full disk and exits 1."""
    import imageio_ffmpeg

    real = imageio_ffmpeg.get_ffmpeg_exe()
    script = tmp_path / f"ffmpeg-{how}"
    if how == "cut":
        body = (f'"{real}" "$@" || exit $?\nfor last; do :; done\n'
                'truncate -s 4096 "$last"\nexit 0\n')
    else:
        body = ('cat > /dev/null\n'
                'echo "[out#0/mp4 @ 0x55d0] Error writing trailer: No space left on device" >&2\n'
                'exit 1\n')
    script.write_text("#!/bin/sh\n" + body)
    script.chmod(script.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", lambda: str(script))
    return script
