"""Small helpers shared by the bench scripts: machine line, timing, peak memory."""

from __future__ import annotations

import os
import platform
import resource
import time
from collections.abc import Callable


def machine() -> str:
    import numpy as np

    try:
        import torch

        tv = f"torch {torch.__version__} ({torch.get_num_threads()} threads)"
    except ImportError:
        tv = "no torch"
    return (f"{platform.node()} · {platform.processor() or platform.machine()} · "
            f"{os.cpu_count()} cores · Python {platform.python_version()} · numpy {np.__version__}"
            f" · {tv}")


def best_of(fn: Callable[[], object], repeat: int = 3) -> float:
    """Best wall time of ``repeat`` runs, seconds."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def peak_rss_mib() -> float:
    """Peak resident memory of this process so far (MiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


#: ``python -c PEAK_CHILD ARGS``: runs ``trmd ARGS`` (or, with ``--snippet CODE``, that code)
#: and on the way out writes this process's VmHWM (kB) to $TRMD_BENCH_HWM
PEAK_CHILD = """
import atexit, os, runpy, sys

def _hwm():
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            with open(os.environ["TRMD_BENCH_HWM"], "w") as fh:
                fh.write(line.split()[1])

atexit.register(_hwm)
if sys.argv[1:2] == ["--snippet"]:
    exec(sys.argv[2])
else:
    sys.argv = ["trmd", *sys.argv[1:]]
    runpy.run_module("trmd_cli", run_name="__main__")
"""


def peak_env(hwm, src=None) -> dict:
    """The environment of a :data:`PEAK_CHILD` run writing its peak to ``hwm``; ``src``: the
    trmd sources to run instead of the installed ones."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST")}
    env["TRMD_BENCH_HWM"] = str(hwm)
    if src is not None:
        env["PYTHONPATH"] = str(src)
    return env


def run_peak(args: list[str], hwm, src=None) -> tuple[float, float, str]:
    """``trmd ARGS`` (or ``--snippet CODE``) in a child: (peak RSS MiB, wall s, stdout)."""
    import subprocess
    import sys
    from pathlib import Path

    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", PEAK_CHILD, *args], capture_output=True,
                          text=True, env=peak_env(hwm, src))
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(args)[:60]} failed (exit {proc.returncode}): "
                         f"{proc.stderr.strip()}")
    peak = int(Path(hwm).read_text()) / 1024
    Path(hwm).unlink()
    return peak, wall, proc.stdout.strip()
