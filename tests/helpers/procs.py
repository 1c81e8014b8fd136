"""Helpers shared by the interrupt tests: real ``python -m trmd_cli`` runs, signalled mid-work."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

#: what a test puts where the run will write, to check it survives byte-identical
PREVIOUS = b"the user's previous output\n"


def temps(folder: Path) -> list[str]:
    """Names of trmd's temporary outputs in ``folder``."""
    return sorted(p.name for p in folder.iterdir() if ".tmp" in p.name)


def launch(*args: str, new_session: bool = False) -> subprocess.Popen:
    """``python -m trmd_cli ARGS``; ``new_session``: as the leader of its own process group (as a
    shell job is). Output goes to unnamed files: a pipe nobody reads until the end would fill up
    and block the run. Collect it with :func:`finish`."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST")}
    out, err = tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")
    proc = subprocess.Popen([sys.executable, "-m", "trmd_cli", *args], stdout=out, stderr=err,
                            text=True, env=env, start_new_session=new_session)
    proc.logs = (out, err)  # type: ignore[attr-defined]
    return proc


def finish(proc: subprocess.Popen, timeout: float = 90.0) -> str:
    """Wait for the run to end; its stderr. A run still going after ``timeout`` s is asked
    for its threads' stacks (SIGUSR1, :func:`trmd_cli.signals.stacks_on_request`), killed,
    and the test fails with them."""
    out, err = proc.logs  # type: ignore[attr-defined]
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        if hasattr(signal, "SIGUSR1"):
            # its worker processes too: they share its stderr
            for pid in [proc.pid, *descendants(proc.pid)]:
                try:
                    os.kill(pid, signal.SIGUSR1)
                except OSError:
                    pass
            time.sleep(2.0)
        proc.kill()
        proc.wait()
        err.seek(0)
        pytest.fail(f"the run had not ended {timeout:g} s later; its stderr and threads:\n"
                    f"{err.read()[-12000:]}")
    err.seek(0)
    text = err.read()
    out.close()
    err.close()
    return text


def children(pid: int) -> list[int]:
    """Child processes of ``pid`` (all its threads'; from /proc, empty elsewhere)."""
    out: list[int] = []
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            out += [int(c) for c in (task / "children").read_text().split()]
    except OSError:
        pass
    return out


def descendants(pid: int) -> list[int]:
    """The processes ``pid`` started, and theirs."""
    return [d for c in children(pid) for d in (c, *descendants(c))]


def wait_until(proc: subprocess.Popen, ready, what: str, timeout: float = 90.0) -> None:
    """Poll ``ready()`` until true; fail if the run ends first or ``timeout`` s pass."""
    end = time.monotonic() + timeout
    while not ready():
        if proc.poll() is not None:
            pytest.fail(f"the run ended (rc {proc.returncode}) before {what}: {finish(proc)}")
        if time.monotonic() > end:
            proc.kill()
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.002)


def group_gone(pgid: int, timeout: float = 10.0) -> bool:
    """No process of the process group ``pgid`` runs (within ``timeout`` s). A zombie counts as
    gone: an init that does not reap keeps the exited ones."""

    def running() -> bool:
        if not Path("/proc").is_dir():
            try:
                os.killpg(pgid, 0)
            except ProcessLookupError:
                return False
            return True
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                fields = stat.read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[2]) == pgid and fields[0] not in "ZX":
                return True
        return False

    end = time.monotonic() + timeout
    while running():
        if time.monotonic() > end:
            return False
        time.sleep(0.05)
    return True
