"""How the process keeps the memory it frees, and how its large arrays are paged.

glibc's ``malloc`` serves a block larger than a threshold (128 KiB at first, raised up to
32 MiB as such blocks are freed) straight from the operating system and gives it back when
freed, and returns the top of its heap once more than twice that lies free. A frame's
temporaries — arrays of a few MiB (2N+1 planes of H×W floats, per-event tables) made and dropped
many times per frame — then come back as fresh pages each time: zero-filled by the kernel, one
fault every 4 KiB. On an esl-cups window EDI's factor ``exp(c·S)/J`` took 6–8 ms that way and
1.5–2.6 ms with the heap keeping its blocks, the same arithmetic.

:func:`keep_freed_memory` raises both thresholds once, at the start of a command. The cost:
up to ``trim_bytes`` of freed memory stays with the process instead of going back to the
system; peak memory is unchanged (what is kept was in use a moment before).

numpy advises the kernel to back every array of 4 MiB or more with huge pages. Where the
kernel's ``transparent_hugepage/defrag`` setting is ``always``, ``madvise`` or
``defer+madvise``, a fault in such an array waits while the kernel compacts memory to find a
free 2 MiB page (numpy issue #31590). On a machine whose memory is fragmented that wait is
long: building the motion method's blur matrix for a 17 px motion (6.4 M entries) took 1.2–2.3 s
of kernel time the first time in a process with the advice, 0.2–0.25 s without it (0.16 s
against 0.25 s on later builds, when huge pages are at hand). :func:`huge_pages_without_stalls`
turns the advice off on such kernels; :func:`tune_memory` does both, once, where a command (or
a process it starts) begins.
"""

from __future__ import annotations

import ctypes
import os
import platform
import sys

__all__ = ["keep_freed_memory", "huge_pages_without_stalls", "tune_memory", "MMAP_BYTES",
           "TRIM_BYTES", "THP_DEFRAG"]

#: blocks below this come from the heap and stay there when freed (glibc's own ceiling for its
#: moving threshold)
MMAP_BYTES = 32 << 20
#: free memory at the top of a heap kept before it is returned
TRIM_BYTES = 128 << 20

# mallopt's parameter numbers (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: variables through which a user sets these thresholds (glibc reads them at start-up)
_USER_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
#: the kernel's setting of what a fault in memory advised for huge pages does when none is free
THP_DEFRAG = "/sys/kernel/mm/transparent_hugepage/defrag"
#: the settings under which that fault waits for memory to be compacted
_STALLING = ("always", "madvise", "defer+madvise")
#: numpy's switch for its huge-page advice (read when numpy is imported)
_NUMPY_ADVICE = "NUMPY_MADVISE_HUGEPAGE"


def keep_freed_memory(mmap_bytes: int = MMAP_BYTES, trim_bytes: int = TRIM_BYTES) -> bool:
    """Let the C heap keep freed blocks below ``mmap_bytes`` and up to ``trim_bytes`` of free
    memory at its top (bytes). Only with glibc, and only when the user has not tuned its
    ``malloc`` already; elsewhere nothing changes.

    Returns:
        Whether the thresholds were set.
    """
    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc":
        return False
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    if any(name in os.environ for name in _USER_SETTINGS) or "threshold" in tunables:
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # (setting the mmap threshold fixes it: glibc stops moving it, so the trim threshold set
    # after it is not moved back either)
    return bool(mallopt(_M_MMAP_THRESHOLD, int(mmap_bytes))) and bool(
        mallopt(_M_TRIM_THRESHOLD, int(trim_bytes)))


def huge_pages_without_stalls(defrag_path: str = THP_DEFRAG) -> bool:
    """Turn numpy's huge-page advice off where a fault in advised memory waits for the kernel
    to compact memory (see the module). Not where the user set ``NUMPY_MADVISE_HUGEPAGE``, nor
    where the kernel's setting cannot be read or does not stall (``defer``, ``never``).

    The variable is set for numpy imported later and for the processes this one starts (the
    helper, ``--jobs`` workers); numpy already imported is switched directly.

    Returns:
        Whether the advice was turned off.
    """
    if _NUMPY_ADVICE in os.environ:
        return False
    try:
        with open(defrag_path, encoding="ascii") as f:
            setting = f.read()
    except (OSError, UnicodeDecodeError):
        return False
    # the file lists every setting, the one in force in brackets
    start, stop = setting.find("["), setting.find("]")
    if start < 0 or stop < start or setting[start + 1:stop] not in _STALLING:
        return False
    os.environ[_NUMPY_ADVICE] = "0"
    if "numpy" in sys.modules:
        try:
            from numpy._core.multiarray import _set_madvise_hugepage
        except ImportError:  # numpy 1.x
            from numpy.core.multiarray import _set_madvise_hugepage
        _set_madvise_hugepage(False)
    return True


def tune_memory() -> tuple[bool, bool]:
    """:func:`keep_freed_memory` and :func:`huge_pages_without_stalls`, as ``trmd`` and the
    processes it starts do when they begin: whether each took effect."""
    return keep_freed_memory(), huge_pages_without_stalls()
