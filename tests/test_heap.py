"""The C heap keeps a frame's temporaries (glibc only)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc",
    reason="the thresholds are glibc's")

# where a 16 MiB block comes from: below the program break it is the heap's (kept when freed),
# above it a mapping of its own (given back when freed, fresh pages next time)
_PROBE = """
import ctypes, sys
libc = ctypes.CDLL(None)
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.sbrk.restype, libc.sbrk.argtypes = ctypes.c_void_p, [ctypes.c_ssize_t]
if sys.argv[1] == "tuned":
    from trmd_cli.heap import keep_freed_memory
    print(keep_freed_memory())
block = libc.malloc(16 << 20)
print("heap" if block < libc.sbrk(0) else "mapped")
"""


def _probe(mode: str, **env: str) -> list[str]:
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True,
                         env={**os.environ, **env}, check=True)
    return out.stdout.split()


def test_blocks_below_the_threshold_come_from_the_heap():
    assert _probe("plain") == ["mapped"]
    assert _probe("tuned") == ["True", "heap"]


def test_a_users_own_malloc_settings_are_kept():
    assert _probe("tuned", MALLOC_MMAP_THRESHOLD_="1048576") == ["False", "mapped"]
    assert _probe("tuned", GLIBC_TUNABLES="glibc.malloc.trim_threshold=1")[0] == "False"


def test_the_command_line_sets_it_before_any_command(monkeypatch):
    from trmd_cli import heap
    from trmd_cli.cli import app

    calls = []
    monkeypatch.setattr(heap, "keep_freed_memory", lambda: calls.append(1) or True)
    monkeypatch.setattr(sys, "argv", ["trmd", "--version"])
    with pytest.raises(SystemExit):
        app.main()
    assert calls == [1]
