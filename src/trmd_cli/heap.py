"""How the process's C heap keeps the memory it frees.

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
"""

from __future__ import annotations

import ctypes
import os
import platform
import sys

__all__ = ["keep_freed_memory", "MMAP_BYTES", "TRIM_BYTES"]

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
