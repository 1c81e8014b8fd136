"""Every file the tool writes goes through here: temporary name in the same folder, then
``os.replace`` — so an interrupted run never leaves a half-written output, and an output folder
is assembled aside and swapped in whole.

Temporary names are recognisable: ``.<output name>.trmd-<pid>-<random>.tmp<suffix>``. Ctrl-C and
SIGTERM remove them on the way out; SIGKILL (or a power cut) cannot, so :func:`check_output`
sweeps the temporaries of *its* output left by processes that no longer run.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import wait as futures_wait
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .errors import InputError, OutputExistsError, TrmdError, WriteError
from .signals import deferred, raise_if_received, recorded_only, shielded

if TYPE_CHECKING:
    from .deblur import FrameResult

__all__ = [
    "atomic_path",
    "atomic_dir",
    "check_output",
    "open_output",
    "write_bytes",
    "write_failure",
    "sweep_stale_temps",
    "to_uint",
    "write_image",
    "write_json",
    "write_text",
    "write_npz",
    "write_result_folder",
    "fmt_fraction",
    "clipped_fraction",
]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _umask()


def check_output(path: str | Path, overwrite: bool,
                 inputs: Iterable[str | Path | None] = (), *, folder: bool | None = None
                 ) -> Path:
    """Refuse an output that exists and is not an empty folder, unless ``overwrite``; refuse,
    whatever ``overwrite`` says, an output that is one of ``inputs`` or a folder holding one
    (writing it would destroy what is being read), and, ``folder`` given, one that exists as
    the other kind (a folder output over a file, a file output over a folder: ``overwrite``
    replaces an output, never a thing of another kind the user may have meant to keep).

    Also removes what killed runs left while writing this same output (see
    :func:`sweep_stale_temps`). Nothing is touched before the checks that refuse.
    """
    path = Path(path)
    refuse_inputs(path, inputs)
    parent = path.parent
    if parent.exists() and not parent.is_dir():
        raise InputError("the output's parent is a file, not a folder", path=parent,
                         hint="choose an output inside a folder")
    if parent.is_dir():
        sweep_stale_temps(path)
    if folder is not None and path.exists() and path.is_dir() != folder:
        raise InputError("the output exists and is not a folder" if folder else
                         "the output exists and is a folder, but a file is to be written here",
                         path=path, hint="choose a folder path" if folder else
                         "give a file name, or remove the folder")
    if path.exists() and not overwrite:
        if not (path.is_dir() and not any(path.iterdir())):
            raise OutputExistsError("output already exists", path=path,
                                    hint="pass `overwrite=True` to replace it, or choose another "
                                    "path")
    if not parent.exists():
        raise InputError("the output's parent folder does not exist", path=parent,
                         hint="create it first")
    return path


def refuse_inputs(path: str | Path, inputs: Iterable[str | Path | None]) -> None:
    """Raise :class:`InputError` when the output ``path`` is one of ``inputs`` (the same file,
    through any link) or a folder that holds one.

    ``overwrite`` never lets an output replace what the command reads: ``trmd voxelize ev.npz
    -o ev.npz`` would replace the events with the voxels, ``trmd deblur b.png d/ev.npz -o d``
    would delete the events with the old folder.
    """
    out = Path(os.path.abspath(path))
    out_real = Path(os.path.realpath(out))
    for given in inputs:
        if given is None:
            continue
        src = Path(os.path.abspath(given))
        src_real = Path(os.path.realpath(src))
        same = src_real == out_real or src == out
        if not same and out.exists() and src.exists():
            with contextlib.suppress(OSError):
                same = os.path.samefile(out, src)
        if same:
            raise InputError(f"the output is the input {given}", path=path,
                             hint="write the output somewhere else (`overwrite=True` never "
                                  "replaces an input)")
        if out_real in src_real.parents or out in src.parents:
            raise InputError(f"the output folder holds the input {given}, which replacing the "
                             "folder would delete", path=path,
                             hint="write the output somewhere else (`overwrite=True` never "
                                  "replaces an input)")


def _temp_prefix(path: Path) -> str:
    return f".{path.name}.trmd-{os.getpid()}-"


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, OSError):
        return True  # someone else's process (or unknowable): leave its files alone
    return True


def sweep_stale_temps(path: str | Path) -> list[Path]:
    """Remove temporaries of ``path`` left by trmd processes that are gone (killed with
    SIGKILL, power cut). Returns what was removed.

    Only names this module makes are touched: ``.<name>.trmd-<pid>-*.tmp*`` whose ``<pid>`` is not
    a running process on this machine. An output folder whose swap was cut between its two
    renames (``.<name>.trmd-<pid>-old.tmp`` present, ``<name>`` absent) is put back first, so
    the previous output survives.
    """
    path = Path(path)
    pattern = re.compile(rf"^\.{re.escape(path.name)}\.trmd-(\d+)-.*\.tmp")
    removed: list[Path] = []
    try:
        candidates = list(path.parent.glob(f".{_glob_escape(path.name)}.trmd-*.tmp*"))
    except OSError:
        return removed
    for tmp in sorted(candidates):
        m = pattern.match(tmp.name)
        if not m or _pid_alive(int(m[1])):
            continue
        try:
            if tmp.name.endswith("-old.tmp") and not path.exists():
                os.replace(tmp, path)
                continue
            if tmp.is_dir() and not tmp.is_symlink():
                shutil.rmtree(tmp)
            else:
                tmp.unlink()
            removed.append(tmp)
        except OSError:
            pass  # another run got there first, or no permission: not ours to fight over
    return removed


def _glob_escape(name: str) -> str:
    return re.sub(r"([*?\[])", r"[\1]", name)


#: what a failed write says when the disk (or a quota, or a file size limit) is full, and when
#: the folder may not be written: read-only mount, no permission
_NO_SPACE = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})
_NOT_ALLOWED = frozenset({errno.EROFS, errno.EACCES, errno.EPERM})
_H5_ERRNO = re.compile(r"errno = (\d+)")


def _errno(e: BaseException) -> int | None:
    """The errno of an OSError, also when a library only quotes it in its message (HDF5:
    ``file write failed: … errno = 28``)."""
    if isinstance(e, OSError) and e.errno:
        return e.errno
    m = _H5_ERRNO.search(str(e)) if isinstance(e, (OSError, RuntimeError)) else None
    return int(m[1]) if m else None


def write_failure(e: BaseException, folder: str | Path,
                  written: str | Path | None = None) -> WriteError | None:
    """The one-line error for ``e`` met while writing an output into ``folder``, or None when
    ``e`` is not a failure to write there.

    A full disk, a quota, a file size limit, a read-only mount: always about the writing.
    No permission: only when ``e`` names no file, or ``written`` (the temporary being written)
    or a file inside it — a permission error about an input is the input's.
    """
    code = _errno(e)
    if code in _NOT_ALLOWED and code != errno.EROFS:
        name = getattr(e, "filename", None)
        if name is not None and written is not None:
            name, written = Path(os.path.abspath(name)), Path(os.path.abspath(written))
            if name != written and written not in name.parents:
                return None
    if code in _NO_SPACE:
        hint = "free some space there, or write the output to another disk"
    elif code in _NOT_ALLOWED:
        hint = "choose a folder you can write to"
    else:
        return None
    return WriteError(f"cannot write here ({os.strerror(code)})", path=folder,
                      hint=f"{hint}; nothing was written")


def _refuse_folder(path: Path) -> None:
    if path.is_dir():
        raise InputError("is a folder, but a file is to be written here", path=path,
                         hint="give a file name, or remove the folder")


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    The temporary name keeps the real suffix so libraries that pick a format by extension work.
    On any exception (Ctrl-C included) the temporary file is removed and ``path`` is untouched.
    """
    path = Path(path)
    _refuse_folder(path)
    suffix = path.suffix if suffix is None else suffix
    tmp_path: Path | None = None
    try:
        with deferred():  # a Ctrl-C right after creation must still find the name
            try:
                fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(path), suffix=f".tmp{suffix}",
                                           dir=path.parent)
            except OSError as e:
                raise _cannot_create(e, path) from None
            tmp_path = Path(tmp)
            os.close(fd)
            os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; outputs look ordinary
        yield tmp_path
        raise_if_received()  # an interrupt something swallowed must still stop the commit
        os.replace(tmp_path, path)
    except BaseException as e:
        if tmp_path is not None:
            with contextlib.suppress(OSError):
                tmp_path.unlink()
        failure = write_failure(e, path.parent, tmp_path) if isinstance(
            e, (OSError, RuntimeError)) else None
        if failure is not None:
            raise failure from None
        raise


def _cannot_create(e: OSError, path: Path) -> TrmdError:
    """Why the temporary file or folder of ``path`` could not be made, as one line."""
    failure = write_failure(e, path.parent)
    if failure is not None:
        return failure
    if e.errno in (errno.ENOENT, errno.ENOTDIR):
        return InputError(f"cannot write here ({e.strerror})", path=path.parent,
                          hint="the output's folder must exist and be a folder")
    return WriteError(f"cannot write here ({e.strerror or e})", path=path.parent,
                      hint="choose another folder for the output")


@contextlib.contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; on success it replaces ``path`` whole.

    An existing ``path`` (already allowed by :func:`check_output`) is removed only after the
    new folder is complete.
    """
    path = Path(path)
    tmp: Path | None = None
    try:
        with deferred():
            try:
                tmp = Path(tempfile.mkdtemp(prefix=_temp_prefix(path), suffix=".tmp",
                                            dir=path.parent))
            except OSError as e:
                raise _cannot_create(e, path) from None
            # mkdtemp makes it private (0700); the finished folder is the user's, as mkdir's
            os.chmod(tmp, 0o777 & ~_UMASK)
        yield tmp
        raise_if_received()
        if path.exists():
            old = path.with_name(f"{_temp_prefix(path)}old.tmp")
            os.replace(path, old)
            try:
                os.replace(tmp, path)
            except BaseException:
                os.replace(old, path)  # the previous output goes back where it was
                raise
            if old.is_dir():
                shutil.rmtree(old, ignore_errors=True)
            else:
                old.unlink(missing_ok=True)
        else:
            os.replace(tmp, path)
    except BaseException as e:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        failure = write_failure(e, path.parent, tmp) if isinstance(
            e, (OSError, RuntimeError)) else None
        if isinstance(e, WriteError) and tmp is not None and e.path is not None and (
                Path(e.path) == tmp or tmp in Path(e.path).parents):
            # a file of the folder could not be written: name the folder the user gave
            failure = WriteError(e.detail, path=path.parent, hint=e.hint)
        if failure is not None:
            raise failure from None
        raise


class _OutputFile(io.RawIOBase):
    """The temporary file of an output, as a raw binary file: every byte trmd writes itself
    reaches the disk through :func:`os.pwrite` here, so that a full disk, a quota or a size limit
    is an ``OSError`` the writer sees (and :func:`atomic_path` turns into one line), never a
    short file. Reads (HDF5 reads back what it wrote) use :func:`os.preadv`."""

    def __init__(self, path: str | Path) -> None:
        super().__init__()
        self.name = str(path)
        self._fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0),
                           0o666)
        self._pos = 0

    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def fileno(self) -> int:
        return self._fd

    def readinto(self, b) -> int:
        if hasattr(os, "preadv"):
            n = os.preadv(self._fd, [b], self._pos)
        else:  # macOS before 11
            view = memoryview(b).cast("B")
            data = os.pread(self._fd, len(view), self._pos)
            n = len(data)
            view[:n] = data
        self._pos += n
        return n

    def write(self, b) -> int:
        view = memoryview(b)
        if view.ndim != 1 or view.itemsize != 1:
            view = view.cast("B")
        done = 0
        while done < len(view):
            done += os.pwrite(self._fd, view[done:], self._pos + done)
        self._pos += done
        return done

    def seek(self, pos: int, whence: int = os.SEEK_SET) -> int:
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self._pos,
                os.SEEK_END: os.fstat(self._fd).st_size}[whence]
        if base + pos < 0:
            raise OSError(errno.EINVAL, "negative seek position")
        self._pos = base + pos
        return self._pos

    def tell(self) -> int:
        return self._pos

    def truncate(self, size: int | None = None) -> int:
        size = self._pos if size is None else int(size)
        os.ftruncate(self._fd, size)
        return size

    def close(self) -> None:
        if not self.closed:
            fd, self._fd = self._fd, -1
            try:
                super().close()
            finally:
                os.close(fd)


def open_output(path: str | Path, text: bool = False):
    """A file object writing ``path`` (a temporary from :func:`atomic_path`) through
    :class:`_OutputFile`: binary, buffered; ``text=True``: UTF-8 text."""
    binary = io.BufferedWriter(_OutputFile(path), buffer_size=1 << 20)
    try:
        raise_if_received()  # BufferedWriter() calls raw.tell() and clears what it raised
    except BaseException:
        binary.close()
        raise
    return io.TextIOWrapper(binary, encoding="utf-8") if text else binary


def write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    path = Path(path)
    with atomic_path(path) as tmp, open_output(tmp) as fh:
        fh.write(data)
    return path


def to_uint(image: np.ndarray, bit_depth: int = 8) -> np.ndarray:
    """[0, 1] float → uint8/uint16, clipping out-of-range values."""
    if bit_depth not in (8, 16):
        raise InputError(f"bit depth must be 8 or 16, got {bit_depth}")
    top = 255 if bit_depth == 8 else 65535
    # fmax drops NaN (→ 0) and −∞; minimum clips +∞ and the rest to 1: nan_to_num and clip
    # in one pass, and the scaling in place (python numbers keep the image's float type;
    # half floats cannot hold 65535 · x + 0.5, nor round to 1/255 exactly)
    image = np.asarray(image)
    out = np.fmax(image, 0.0, dtype=np.float32 if image.dtype == np.float16 else None)
    np.minimum(out, 1.0, out=out)
    out *= top
    out += 0.5
    return out.astype(np.uint8 if bit_depth == 8 else np.uint16)


def _image_bytes(path: Path, image: np.ndarray, bit_depth: int) -> bytes:
    """The encoded file of ``image`` in the format ``path``'s suffix names."""
    import cv2

    shape = np.shape(image)
    if not (len(shape) == 2 or (len(shape) == 3 and shape[2] in (1, 3))):
        raise InputError(f"an image of shape {shape}: expected (H, W) gray or (H, W, 3) RGB",
                         path=path)
    arr = image if image.dtype in (np.uint8, np.uint16) else to_uint(image, bit_depth)
    if arr.ndim == 3:
        arr = arr[..., ::-1]  # RGB → OpenCV's BGR
    try:
        ok, data = cv2.imencode(path.suffix, np.ascontiguousarray(arr))
    except cv2.error:
        ok = False
    if not ok:
        raise InputError("could not encode image", path=path,
                         hint="use .png, .jpg or .tif")
    return data.tobytes()


def write_image(path: str | Path, image: np.ndarray, bit_depth: int = 8) -> Path:
    """Write a [0, 1] float (or uint8/uint16) image, (H, W) or (H, W, 3) RGB, atomically."""
    path = check_image_suffix(path)
    # encoded in memory before the temporary file exists (an error names the path the user
    # gave), then written by us: ``cv2.imwrite`` on a full disk may report success over a
    # short file
    data = _image_bytes(path, image, bit_depth)
    with atomic_path(path) as tmp, open_output(tmp) as fh:
        fh.write(data)
    return path


def check_image_suffix(path: str | Path) -> Path:
    """``path``, refused unless its suffix names an image format trmd writes (check it before
    any work whose result the picture goes with)."""
    from .read.frames import IMAGE_EXTENSIONS

    path = Path(path)
    if path.suffix.lower() not in IMAGE_EXTENSIONS:
        raise InputError(f"cannot write a {path.suffix or 'suffix-less'} picture", path=path,
                         hint="use .png, .jpg or .tif")
    return path


def write_json(path: str | Path, obj) -> Path:
    return write_text(path, _json_text(obj))


def _json_text(obj) -> str:
    """``obj`` as the JSON trmd writes: indented, numpy values as numbers, a final newline."""
    return json.dumps(obj, indent=2, default=_json_default) + "\n"


def write_text(path: str | Path, text: str) -> Path:
    path = Path(path)
    with atomic_path(path) as tmp, open_output(tmp, text=True) as fh:
        fh.write(text)
    return path


def write_npz(path: str | Path, compress: bool = False, **arrays) -> Path:
    path = Path(path)
    with atomic_path(path, suffix=".npz") as tmp:
        with open_output(tmp) as fh:
            (np.savez_compressed if compress else np.savez)(fh, **arrays)
    return path


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


# --------------------------------------------------------------------------------------------
# The result folder of one deblurred frame


def clipped_fraction(frames: np.ndarray) -> float:
    """Fraction of values above 1 ([0, 1] intensity): they are clipped when written."""
    frames = np.asarray(frames)
    return np.count_nonzero(frames > 1.0) / frames.size if frames.size else 0.0


#: clipping below this fraction of the values is a few specular pixels: not worth a warning
#: (the exact fraction is in meta.json)
CLIPPED_WORTH_SAYING = 1e-4


def clipped_message(fraction: float) -> str | None:
    """The warning for a mean clipped fraction, or None when too small to matter."""
    if fraction < CLIPPED_WORTH_SAYING:
        return None
    return f"{100 * fraction:.2f} % of output values were above 1 and were clipped to white"


def _contrast_origin(estimate) -> dict:
    """meta.json's word on where c came from: estimated, or the default a window with too few
    events to estimate from fell back to (``contrast_default``), else given."""
    default = estimate.contrast_default
    return {"contrast_estimated": estimate.contrast_estimated and not default,
            **({"contrast_default": True} if default else {})}


def write_result_folder(folder: str | Path, result: FrameResult, *, bit_depth: int = 8,
                        compare: bool = False, meta: dict | None = None) -> dict:
    """Write one result into ``folder``: frame_000.png … frame_{K-1}.png, sharp.png (the
    middle frame), timestamps.txt (µs on the events' clock), meta.json, [compare.png:
    blurry | sharp]. Returns this frame's part of the meta.

    ``folder`` must exist and be a temporary that the caller commits whole
    (:func:`atomic_dir`): its files are written in place, not each through a temporary of
    its own (which cost as much as encoding two of the frames).

    Binned events have no clock: timestamps.txt then has a ``fraction`` column (of the
    exposure, 0 = start, 1 = end, as exact floats) instead of ``time_us``, and the meta says
    ``"binned": true`` with ``fractions`` instead of ``exposure_us`` / ``instants_us``.
    """
    from .viz import strip

    folder = Path(folder)
    frames = result.frames
    width = max(3, len(str(len(frames) - 1)))
    binned = result.exposure is None
    lines = ["# file fraction (of the exposure: 0 = start, 1 = end; binned events, no event "
             "clock)" if binned else "# file time_us (event clock)"]
    names = [f"frame_{k:0{width}d}.png" for k in range(len(frames))]
    # all frames to integers in one pass over the stack (the same numbers as frame by frame);
    # encoding and writing are most of the rest and release the GIL: two frames at a time,
    # on threads kept between calls, each writing the files of its frame
    stack = np.asarray(frames)
    ints = to_uint(stack, bit_depth) if stack.dtype.kind == "f" else stack

    def encoded(k: int) -> None:
        data = _image_bytes(folder / names[k], ints[k], bit_depth)
        _write_in_place(folder / names[k], data)
        if k == result.middle_index:  # sharp.png: the same bytes, not a second encoding
            _write_in_place(folder / "sharp.png", data)

    # every job ends before a failure (or an interrupt while waiting) goes up: the caller then
    # removes the folder, and no file of a job still running may appear in it afterwards. A
    # Ctrl-C is held while the pool is handed the jobs and waited on (``shielded``): raised
    # inside their locks it left one held, a job could not finish, and the run waited for ever
    with shielded():
        jobs = [_encoders().submit(encoded, k) for k in range(len(names))]
    try:
        with shielded():
            futures_wait(jobs)
    except BaseException:
        for job in jobs:
            job.cancel()
        futures_wait(jobs)
        raise
    for job in jobs:
        job.result()
    times = [fmt_fraction(t) for t in result.instants_us] if binned else \
        instant_texts(result.exposure, len(names))
    for name, t in zip(names, times, strict=True):
        lines.append(f"{name} {t}")
    _write_in_place(folder / "timestamps.txt", ("\n".join(lines) + "\n").encode())
    if compare:
        picture = strip([result.blurry, result.middle], ("blurry", "sharp"), keep_float=True)
        _write_in_place(folder / "compare.png",
                        _image_bytes(folder / "compare.png", picture, bit_depth))
    if binned:
        info = {
            "frame": result.name,
            "index": result.index,
            "binned": True,
            "frames": len(frames),
            "fractions": [float(t) for t in result.instants_us],
            "contrast": result.estimate.contrast,
            **_contrast_origin(result.estimate),
            # net counts per pixel and bin: the events are at least this many
            "abs_count": result.num_events,
            "passthrough": result.passthrough,
            "clipped_fraction": clipped_fraction(stack),
        }
    else:
        info = {
            "frame": result.name,
            "index": result.index,
            "exposure_us": [result.exposure.start_us, result.exposure.end_us],
            "frames": len(frames),
            "instants_us": [float(t) for t in result.instants_us],
            "contrast": result.estimate.contrast,
            **_contrast_origin(result.estimate),
            **({} if result.estimate.fallback_contrast is None else
               {"fallback_contrast": result.estimate.fallback_contrast}),
            "events": result.num_events,
            "hot_pixels": result.estimate.hot_pixels,
            "passthrough": result.passthrough,
            "clipped_fraction": clipped_fraction(stack),
        }
    full = {**(meta or {}), **info}
    _write_in_place(folder / "meta.json", _json_text(full).encode())
    return info


def _write_in_place(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` in a folder committed whole: a failure to write is one line
    (:func:`write_failure`), and the caller's temporary folder is dropped with what it held."""
    raise_if_received()
    try:
        with _OutputFile(path) as fh:
            fh.write(data)
    except OSError as e:
        failure = write_failure(e, path.parent, path)
        if failure is not None:
            raise failure from None
        raise


_POOL: dict[int, ThreadPoolExecutor] = {}


def _encoders() -> ThreadPoolExecutor:
    """Two threads for image encoding, made once per process (starting threads for every
    result folder cost a tenth of its writing). By process id: a forked worker does not
    inherit its parent's threads, only their record."""
    pid = os.getpid()
    if pid not in _POOL:
        _POOL[pid] = ThreadPoolExecutor(max_workers=2, thread_name_prefix="trmd-encode")
    return _POOL[pid]


def instant_texts(exposure, count: int) -> list[str]:
    """The ``count`` instants spread evenly over ``exposure``, ends included (one: its
    middle), as written in timestamps.txt: µs to the thousandth, from whole numbers — a float64
    near 1.5e15 µs (an epoch clock) resolves only a quarter of a microsecond."""
    start, span = int(exposure.start_us), int(exposure.duration_us)
    if count == 1:
        return [exact_us_text(start, span, 2)]
    return [exact_us_text(start, k * span, count - 1) for k in range(count)]


def exact_us_text(base: int, num: int, den: int) -> str:
    """``base + num / den`` µs (whole numbers, ``num`` ≥ 0, ``den`` > 0) written to the
    thousandth, rounded half up, without a float in between."""
    milli = (num * 2000 + den) // (2 * den)
    whole, frac = divmod(milli, 1000)
    return f"{base + whole}" + (f".{frac:03d}".rstrip("0") if frac else "")


def fmt_fraction(f: float) -> str:
    """A fraction of the exposure as written in timestamps.txt: the shortest decimal that
    reads back as the same float (``0``, ``0.5``, ``0.16666666666666666``), never rounded."""
    f = float(f)
    return "0" if f == 0 else "1" if f == 1 else repr(f)


# --------------------------------------------------------------------------------------------
# Event files in the project's own layouts (docs/formats.md)

#: version of the trmd HDF5 layout written here
H5_LAYOUT_VERSION = 1


class _HDF5File(_OutputFile):
    """The temporary file of an HDF5 output, handed to h5py as a file object.

    HDF5 calls :meth:`write` and :meth:`readinto` from C. An exception there (a full disk, a
    Ctrl-C that lands in the callback) leaves HDF5 with metadata it cannot flush, and h5py then
    dies with SIGSEGV while closing the file. So a failure is recorded and the call pretends to
    have succeeded — every later write is dropped, the output is abandoned anyway — and
    :class:`H5Writer` raises the recorded failure as soon as HDF5 has returned."""

    failure: BaseException | None = None

    def write(self, b) -> int:
        size = memoryview(b).nbytes
        if self.failure is None:
            try:
                return super().write(b)
            except BaseException as e:  # noqa: BLE001 - raised by H5Writer once HDF5 returns
                self.failure = e
        return size

    def readinto(self, b) -> int:
        for _ in range(2):  # an interrupt landing here: finish the read, raise it later
            try:
                return super().readinto(b)
            except BaseException as e:  # noqa: BLE001 - raised by H5Writer once HDF5 returns
                if self.failure is None:
                    self.failure = e
                if not isinstance(e, KeyboardInterrupt):
                    break
        memoryview(b).cast("B")[:] = b"\0" * memoryview(b).nbytes
        return memoryview(b).nbytes


class H5Writer:
    """Incremental writer of the trmd HDF5 layout (atomic: a temp file renamed on close).

    Layout: root attrs ``format="trmd"``, ``version``, ``width``, ``height``; ``events/x,y``
    uint16, ``events/t`` int64 µs, ``events/p`` int8 ±1; ``frames/blurry`` (K, H, W[, 3])
    float32 [0, 1]; ``frames/exposure_start``, ``frames/exposure_end`` (K,) int64 µs; optional
    ``frames/sharp`` (K, 2N+1, H, W[, 3]) float32 and ``frames/contrast`` (K,) float32 (the
    simulator's true mean contrast threshold); optional ``frames/motion`` (K, J, 3, 3) float64,
    the simulator's true camera path over each exposure: homographies mapping a pixel of the
    middle frame (exposure fraction ½) to where that point is at exposure fraction ``j/(J−1)``,
    output pixels (pixel centres at integers), ``H[2, 2] = 1`` (J = 33 from ``trmd simulate``;
    :class:`~trmd_cli.motion.SampledMotion` reads it); ``windows/start_us``, ``windows/end_us``
    (K,) int64 µs: exposure windows stored without frames. Events of consecutive samples share
    one timeline. Readers treat every optional dataset as optional: files without
    ``frames/motion`` (older ones, videos, recordings) read as before.

    A write that fails (full disk, read-only folder) raises :class:`~trmd_cli.errors.WriteError`
    from the call that met it, and the temporary file is removed.

    Usage::

        with H5Writer("out.h5", 346, 260) as w:
            w.add_events(stream)
            w.add_frame(blurry, Exposure(0, 10_000), sharp=gt, contrast=0.2, motion=path)
    """

    def __init__(self, path: str | Path, width: int, height: int, *, compression: str | None = None,
                 attrs: dict | None = None):
        import h5py

        self.path = Path(path)
        self.width, self.height = int(width), int(height)
        self._f = None
        self._file: _HDF5File | None = None
        self._quiet = None
        self._ctx = atomic_path(self.path, suffix=".h5")
        self._tmp = self._ctx.__enter__()
        # while HDF5 holds the file, Ctrl-C and kill are raised between h5py calls only
        # (:func:`~trmd_cli.signals.recorded_only`; :meth:`_guard` raises them)
        self._quiet = recorded_only()
        self._quiet.__enter__()
        try:
            with self._guard():
                self._file = _HDF5File(self._tmp)
                self._f = h5py.File(self._file, "w")
                self._comp = compression
                self._f.attrs.update({"format": "trmd", "version": H5_LAYOUT_VERSION,
                                      "width": self.width, "height": self.height,
                                      **(attrs or {})})
                ev = self._f.create_group("events")
                for key, dt in (("x", "u2"), ("y", "u2"), ("t", "i8"), ("p", "i1")):
                    ev.create_dataset(key, (0,), dtype=dt, maxshape=(None,), chunks=(1 << 16,),
                                      compression=compression)
        except BaseException as e:
            self._abandon(e)
            raise
        self._frames = None
        self._last_t = -1

    @contextlib.contextmanager
    def _guard(self) -> Iterator[None]:
        """Run h5py calls; raise what the file met inside them (see :class:`_HDF5File`), then
        a Ctrl-C or ``kill`` received meanwhile."""
        try:
            yield
        except BaseException:
            if self._file is not None and self._file.failure is not None:
                self._raise_failure()
            raise
        if self._file is not None and self._file.failure is not None:
            self._raise_failure()
        raise_if_received()

    def _raise_failure(self):
        e = self._file.failure
        failure = write_failure(e, self.path.parent, self._tmp)
        if failure is not None:
            raise failure from None
        raise e

    def add_events(self, stream) -> None:
        """Events after those added before, of the file's sensor (what its reader would
        refuse is refused here)."""
        if len(stream) == 0:
            return
        if int(stream.t[0]) < self._last_t or (np.diff(stream.t) < 0).any():
            raise InputError("events must be added in time order")
        if int(stream.x.max()) >= self.width or int(stream.y.max()) >= self.height:
            raise InputError(f"events reach ({int(stream.x.max())}, {int(stream.y.max())}), "
                             f"outside the file's {self.width}x{self.height} sensor")
        with self._guard():
            ev = self._f["events"]
            n0 = ev["t"].shape[0]
            for key in "xytp":
                ds = ev[key]
                ds.resize((n0 + len(stream),))
                ds[n0:] = getattr(stream, key)
        self._last_t = int(stream.t[-1])

    def add_frame(self, blurry: np.ndarray, exposure, sharp: np.ndarray | None = None,
                  contrast: float | None = None, motion: np.ndarray | None = None) -> None:
        """One frame: ``blurry`` (H, W[, 3]) [0, 1], its ``exposure`` (µs), and optionally
        its 2N+1 ``sharp`` frames, the true ``contrast`` and the true camera path ``motion``
        (J, 3, 3) at exposure fractions ``j/(J−1)`` (see the class docstring). What the first
        frame has, every frame must have."""
        blurry = np.asarray(blurry, np.float32)
        if blurry.shape[:2] != (self.height, self.width):
            raise InputError(f"frame is {blurry.shape[1]}x{blurry.shape[0]}, the file's sensor "
                             f"is {self.width}x{self.height}")
        if not np.isfinite(blurry).all():
            raise InputError("frame holds NaN or infinite pixel values",
                             hint="pixels are intensities in [0, 1]")
        if motion is not None:
            motion = np.asarray(motion, np.float64)
            if motion.ndim != 3 or motion.shape[1:] != (3, 3) or motion.shape[0] < 2:
                raise InputError(f"the camera path has shape {motion.shape}, expected (J ≥ 2, "
                                 "3, 3) homographies")
        with self._guard():
            self._add_frame(blurry, exposure, sharp, contrast, motion)

    def _add_frame(self, blurry, exposure, sharp, contrast, motion=None) -> None:
        if self._frames is None:
            g = self._f.create_group("frames")
            chunk = (1, *blurry.shape)
            g.create_dataset("blurry", (0, *blurry.shape), "f4", maxshape=(None, *blurry.shape),
                             chunks=chunk, compression=self._comp)
            g.create_dataset("exposure_start", (0,), "i8", maxshape=(None,))
            g.create_dataset("exposure_end", (0,), "i8", maxshape=(None,))
            if sharp is not None:
                s = np.shape(sharp)
                g.create_dataset("sharp", (0, *s), "f4", maxshape=(None, *s), chunks=(1, *s),
                                 compression=self._comp)
            if contrast is not None:
                g.create_dataset("contrast", (0,), "f4", maxshape=(None,))
            if motion is not None:
                g.create_dataset("motion", (0, *motion.shape), "f8",
                                 maxshape=(None, *motion.shape), chunks=(1, *motion.shape))
            self._frames = g
        g = self._frames
        k = g["blurry"].shape[0]
        for name, value in (("blurry", blurry), ("exposure_start", exposure.start_us),
                            ("exposure_end", exposure.end_us), ("sharp", sharp),
                            ("contrast", contrast), ("motion", motion)):
            if name not in g:
                if value is not None:
                    raise InputError(f"'{name}' given for frame {k} but not for the first frame")
                continue
            if value is None:
                raise InputError(f"'{name}' missing for frame {k} (the first frame had it)")
            if name == "motion" and np.shape(value) != g[name].shape[1:]:
                raise InputError(f"the camera path of frame {k} has shape {np.shape(value)}, "
                                 f"the first frame's {g[name].shape[1:]}")
            g[name].resize((k + 1, *g[name].shape[1:]))
            g[name][k] = value

    def add_windows(self, exposures) -> None:
        """Exposure windows stored without frames (``windows/start_us``, ``windows/end_us``):
        what a file that knows when its exposures were, but holds no images, carries."""
        starts = np.array([e.start_us for e in exposures], np.int64)
        ends = np.array([e.end_us for e in exposures], np.int64)
        with self._guard():
            if "windows" in self._f:
                raise InputError("exposure windows are already stored in this file")
            g = self._f.create_group("windows")
            g.create_dataset("start_us", data=starts)
            g.create_dataset("end_us", data=ends)

    def close(self, ok: bool = True) -> None:
        if self._f is None:
            return
        if not ok:
            self._abandon(RuntimeError("aborted"))
            return
        try:
            with self._guard():
                f, self._f = self._f, None
                f.close()
                self._file.close()
        except BaseException as e:
            self._abandon(e)
            raise
        self._release()
        self._ctx.__exit__(None, None, None)

    def _abandon(self, exc: BaseException) -> None:
        """Close what is open (HDF5 can: failed writes were pretended done) and remove the
        temporary file; ``exc`` is what went wrong (atomic_path re-raises it: swallowed here,
        the caller raises its own)."""
        try:
            if self._f is not None:
                self._f.close()
        except BaseException:  # noqa: BLE001 - already failing
            pass
        finally:
            self._f = None
            if self._file is not None:
                with contextlib.suppress(BaseException):
                    self._file.close()
            with contextlib.suppress(BaseException):
                self._ctx.__exit__(type(exc), exc, None)
            self._release()

    def _release(self) -> None:
        """HDF5 is done with the file: signals raise where they land again."""
        if self._quiet is not None:
            quiet, self._quiet = self._quiet, None
            quiet.__exit__(None, None, None)

    def __enter__(self) -> "H5Writer":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close(True)
        else:
            self._abandon(exc)


def write_h5(path: str | Path, stream, *, blurry=None, exposures=None, sharp=None,
             contrast=None, motion=None, compression: str | None = None) -> Path:
    """Write events (and optionally frames, with ``motion`` (K, J, 3, 3) their true camera
    paths) in the trmd HDF5 layout, atomically."""
    if blurry is not None and (exposures is None or len(exposures) != len(blurry)):
        raise InputError(f"{len(blurry)} frames but "
                         f"{'no' if exposures is None else len(exposures)} exposure windows",
                         hint="give one exposure window per frame")
    with H5Writer(path, stream.width, stream.height, compression=compression) as w:
        w.add_events(stream)
        for k in range(0 if blurry is None else len(blurry)):
            w.add_frame(blurry[k], exposures[k], None if sharp is None else sharp[k],
                        None if contrast is None else float(np.ravel(contrast)[k]),
                        None if motion is None else motion[k])
    return Path(path)


def write_events_npz(path: str | Path, stream, exposures=None, compress: bool = False) -> Path:
    """Events as ``x, y, t (int64 µs), p (int8), width, height`` [+ exposure_start/end]."""
    extra = {}
    if exposures:
        extra = {"exposure_start": np.array([e.start_us for e in exposures], np.int64),
                 "exposure_end": np.array([e.end_us for e in exposures], np.int64)}
    return write_npz(path, compress, x=stream.x, y=stream.y, t=stream.t, p=stream.p,
                     width=np.int64(stream.width), height=np.int64(stream.height), **extra)


def write_events_text(path: str | Path, stream) -> Path:
    """E2VID-style text: first line ``W H``, then ``t x y p`` with t in float seconds and p 0/1.
    Read back exactly for times below about 4.5·10¹⁵ µs (142 years: float seconds resolve a
    microsecond there).

    Raises:
        InputError: no events (a text file of none reads as no event file at all).
    """
    path = Path(path)
    if len(stream) == 0:
        raise InputError("no events to write: a text file without event lines reads back as "
                         "no event file", hint="write an empty recording as .npz or .h5")
    with atomic_path(path) as tmp, open_output(tmp, text=True) as fh:
        fh.write(f"{stream.width} {stream.height}\n")
        # seconds with µs resolution, written via integer parts so no float rounding
        sec, us = np.divmod(stream.t, 1_000_000)
        cols = np.stack([sec, us, stream.x, stream.y, (stream.p > 0)], 1).astype(np.int64)
        lines = "\n".join(f"{a}.{b:06d} {c} {d} {e}" for a, b, c, d, e in cols.tolist())
        fh.write(lines + "\n")
    return path
