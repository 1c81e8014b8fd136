"""The C heap keeps a frame's temporaries (glibc only); numpy's huge-page advice is off where
the kernel would stall on it."""

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
    monkeypatch.setattr(heap, "tune_memory", lambda: calls.append(1) or (True, True))
    monkeypatch.setattr(sys, "argv", ["trmd", "--version"])
    with pytest.raises(SystemExit):
        app.main()
    assert calls == [1]


# numpy's advice as a process sees it after ``huge_pages_without_stalls`` with the kernel's
# setting read from argv[1], and as a process it starts sees it
_ADVICE = """
import os, subprocess, sys
import numpy
from numpy._core.multiarray import _set_madvise_hugepage
from trmd_cli.heap import huge_pages_without_stalls
done = huge_pages_without_stalls(sys.argv[1])
was = _set_madvise_hugepage(True)  # returns the setting it replaces
child = subprocess.run([sys.executable, "-c", "import numpy; from numpy._core.multiarray "
                        "import _set_madvise_hugepage as s; print(s(True))"],
                       capture_output=True, text=True, check=True).stdout.strip()
print(done, was, child, os.environ.get("NUMPY_MADVISE_HUGEPAGE"))
"""


@pytest.mark.parametrize(("setting", "want"), [
    ("always defer defer+madvise [madvise] never", ["True", "False", "False", "0"]),
    ("[always] defer defer+madvise madvise never", ["True", "False", "False", "0"]),
    ("always defer [defer+madvise] madvise never", ["True", "False", "False", "0"]),
    # the kernel does not wait for compaction: numpy's advice stays
    ("always [defer] defer+madvise madvise never", ["False", "default", "default", "None"]),
    ("always defer defer+madvise madvise [never]", ["False", "default", "default", "None"]),
])
def test_huge_page_advice_off_where_the_kernel_would_stall(tmp_path, setting, want):
    pytest.importorskip("numpy._core.multiarray")
    defrag = tmp_path / "defrag"
    defrag.write_text(setting + "\n")
    assert _advice(defrag) == [_default() if w == "default" else w for w in want]


def _advice(defrag, **env: str) -> list[str]:
    """:data:`_ADVICE`'s words with the kernel's setting read from ``defrag``, in an
    environment without NUMPY_MADVISE_HUGEPAGE unless ``env`` gives it."""
    base = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    return subprocess.run([sys.executable, "-c", _ADVICE, str(defrag)], capture_output=True,
                          text=True, env={**base, **env}, check=True).stdout.split()


def _default() -> str:
    """numpy's own advice in a process left alone (on on Linux 4.6 and later)."""
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    return subprocess.run([sys.executable, "-c", "import numpy; from numpy._core.multiarray "
                           "import _set_madvise_hugepage as s; print(s(True))"],
                          capture_output=True, text=True, env=env, check=True).stdout.strip()


def test_huge_page_advice_left_to_the_user_and_to_unreadable_settings(tmp_path):
    default = _default()
    assert _advice(tmp_path / "none") == ["False", default, default, "None"]
    defrag = tmp_path / "defrag"
    defrag.write_text("always defer defer+madvise [madvise] never\n")
    # the user's 1: on
    assert _advice(defrag, NUMPY_MADVISE_HUGEPAGE="1") == ["False", "True", "True", "1"]
