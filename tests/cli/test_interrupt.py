"""Interrupted runs: Ctrl-C (SIGINT), ``kill`` (SIGTERM) and ``kill -9`` (SIGKILL) in the middle
of `trmd convert` / `trmd voxelize` leave a previous output byte-identical and no temporary files
(SIGKILL cannot clean up: its temporary file is swept by the next run that writes that output).

Real processes (``python -m trmd_cli``) are signalled at a known point: once their temporary
output file exists (convert to text writes for seconds), or once they hold the HDF5 input open
(voxelize reads it window by window). In-process runs with a KeyboardInterrupt injected at chosen
places cover the writers whose work is too quick to catch from outside.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.procs import PREVIOUS, finish, group_gone, launch, temps, wait_until
from trmd_cli.cli.app import app
from trmd_cli.events import make_stream
from trmd_cli.write import sweep_stale_temps, write_events_npz, write_h5

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="signals and /proc as on Linux")

W, H = 64, 48
runner = CliRunner()


def stream(n: int, seed: int = 0, span_us: int = 10**7):
    rng = np.random.default_rng(seed)
    return make_stream(rng.integers(0, W, n), rng.integers(0, H, n),
                       np.sort(rng.integers(0, span_us, n)), rng.integers(0, 2, n), W, H)


@pytest.fixture(scope="module")
def big_npz(tmp_path_factory) -> Path:
    """1M events: converting them to text takes seconds (Python formats every line)."""
    path = tmp_path_factory.mktemp("src") / "big.npz"
    write_events_npz(path, stream(1_000_000))
    return path


@pytest.fixture(scope="module")
def windows_h5(tmp_path_factory) -> Path:
    """HDF5 read lazily, with 3000 stored exposure windows: voxelizing loops for about a second
    while the file is held open."""
    path = tmp_path_factory.mktemp("src") / "windows.h5"
    write_h5(path, stream(300_000))
    starts = np.linspace(0, 10**7 - 4_000, 3000).astype(np.int64)
    with h5py.File(path, "a") as f:
        f["frames/exposure_start"] = starts
        f["frames/exposure_end"] = starts + 3_000
    return path


def holds_open(pid: int, path: Path) -> bool:
    try:
        fds = list(Path(f"/proc/{pid}/fd").iterdir())
    except OSError:
        return False
    for fd in fds:
        try:
            if os.readlink(fd) == str(path):
                return True
        except OSError:
            continue
    return False


def one_line(stderr: str) -> str:
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, stderr
    assert "Traceback" not in stderr
    return lines[0]


# -- real processes ------------------------------------------------------------------------------


@pytest.mark.parametrize("sig,code,word", [(signal.SIGINT, 130, "interrupted"),
                                           (signal.SIGTERM, 143, "terminated")])
def test_convert_interrupted_while_writing(tmp_path, big_npz, sig, code, word):
    out = tmp_path / "events.txt"
    out.write_bytes(PREVIOUS)
    proc = launch("convert", str(big_npz), "-o", str(out), "--overwrite")
    wait_until(proc, lambda: temps(tmp_path), "the temporary output appeared")
    proc.send_signal(sig)
    err = finish(proc, timeout=60)
    assert proc.returncode == code, err
    assert word in one_line(err)
    assert out.read_bytes() == PREVIOUS
    assert temps(tmp_path) == []


def test_convert_killed_leaves_a_temp_that_the_next_run_sweeps(tmp_path, big_npz):
    out = tmp_path / "events.txt"
    out.write_bytes(PREVIOUS)
    proc = launch("convert", str(big_npz), "-o", str(out), "--overwrite")
    wait_until(proc, lambda: temps(tmp_path), "the temporary output appeared")
    proc.kill()
    finish(proc, timeout=60)
    assert proc.returncode == -signal.SIGKILL
    assert out.read_bytes() == PREVIOUS
    # SIGKILL cannot be caught: its half-written temporary stays, named for output and process
    left = temps(tmp_path)
    assert left and all(n.startswith(f".events.txt.trmd-{proc.pid}-") for n in left), left

    small = tmp_path / "small.npz"
    write_events_npz(small, stream(100))
    r = runner.invoke(app, ["convert", str(small), "-o", str(out), "--overwrite"])
    assert r.exit_code == 0, r.output
    assert temps(tmp_path) == []
    assert out.read_bytes().startswith(b"64 48\n") and out.read_bytes().count(b"\n") == 101


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL])
def test_voxelize_interrupted_while_reading(tmp_path, windows_h5, sig):
    out = tmp_path / "voxels.npz"
    out.write_bytes(PREVIOUS)
    proc = launch("voxelize", str(windows_h5), "-o", str(out), "--n", "1", "--overwrite")
    wait_until(proc, lambda: holds_open(proc.pid, windows_h5), "the input was opened")
    proc.send_signal(sig)
    err = finish(proc, timeout=60)
    if sig == signal.SIGINT:
        assert proc.returncode == 130 and "interrupted" in one_line(err), err
    else:
        assert proc.returncode == -signal.SIGKILL
    assert out.read_bytes() == PREVIOUS
    assert temps(tmp_path) == []


# -- interrupts injected in-process at the places too quick to hit from outside ------------------


@pytest.fixture
def small_sources(tmp_path) -> dict[str, Path]:
    s = stream(20_000, span_us=100_000)
    npz = tmp_path / "src.npz"
    write_events_npz(npz, s)
    h5 = tmp_path / "src.h5"
    write_h5(h5, s)
    return {"npz": npz, "h5": h5}


def run_interrupted(args: list[str], out: Path, out_survives: bool = True) -> None:
    out.write_bytes(PREVIOUS)
    r = runner.invoke(app, [*args, "-o", str(out), "--overwrite"])
    assert r.exit_code == 130, (r.exit_code, r.output)
    assert "interrupted; no partial output was left" in one_line(r.stderr)
    if out_survives:
        assert out.read_bytes() == PREVIOUS
    assert temps(out.parent) == []


def test_h5_writer_interrupted_between_chunks(tmp_path, small_sources, monkeypatch):
    """convert → .h5: the writer's temp file exists from the start; chunks arrive one by one."""
    from trmd_cli import write
    from trmd_cli.read import hdf5

    real_add, real_chunks, calls = write.H5Writer.add_events, hdf5.HDF5Recording.iter_chunks, []

    def add_events(self, chunk):
        calls.append(len(chunk))
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_add(self, chunk)

    monkeypatch.setattr(write.H5Writer, "add_events", add_events)
    monkeypatch.setattr(hdf5.HDF5Recording, "iter_chunks",
                        lambda self, max_events=1 << 22: real_chunks(self, 5_000))
    run_interrupted(["convert", str(small_sources["h5"])], tmp_path / "out.h5")
    assert calls == [5_000, 5_000]


@pytest.mark.parametrize("where", ["np.savez", "image bytes"])
def test_voxelize_interrupted_while_writing(tmp_path, small_sources, monkeypatch, where):
    """Interrupted inside the writer of the voxels, or of the preview image written after them:
    the output being written stays as it was (a finished one is complete)."""
    from trmd_cli import write

    if where == "np.savez":
        def partial_savez(fh, **arrays):
            fh.write(b"PK\x03\x04 half an archive")
            raise KeyboardInterrupt

        monkeypatch.setattr(write.np, "savez", partial_savez)
    else:
        real_write = write._OutputFile.write

        def failing_write(self, data):  # the encoded image's bytes reach the disk, half way
            if not self.name.endswith(".png"):
                return real_write(self, data)
            real_write(self, bytes(data)[:8])
            raise KeyboardInterrupt

        monkeypatch.setattr(write._OutputFile, "write", failing_write)
    preview = tmp_path / "preview.png"
    preview.write_bytes(PREVIOUS)
    out = tmp_path / "voxels.npz"
    run_interrupted(["voxelize", str(small_sources["npz"]), "--exposure", "0", "90000",
                     "--preview", str(preview)], out, out_survives=where == "np.savez")
    assert preview.read_bytes() == PREVIOUS
    if where == "image bytes":
        with np.load(out) as z:  # finished before the interrupt: the new, complete voxels
            assert z["voxels"].shape == (1, 6, H, W)


def test_sweep_only_touches_dead_processes_temps_of_that_output(tmp_path):
    out = tmp_path / "events.h5"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    mine, theirs = os.getpid(), dead.pid
    files = {
        f".events.h5.trmd-{theirs}-abc123.tmp.h5": True,    # killed run of this output
        f".events.h5.trmd-{mine}-def456.tmp.h5": False,     # a run still going (this one)
        f".other.h5.trmd-{theirs}-abc123.tmp.h5": False,    # another output
        "events.h5.tmp": False,                             # not a name trmd makes
    }
    for name in files:
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / f".events.h5.trmd-{theirs}-xyz789.tmp").mkdir()  # a folder being assembled
    removed = sweep_stale_temps(out)
    assert sorted(p.name for p in removed) == sorted(
        [n for n, gone in files.items() if gone] + [f".events.h5.trmd-{theirs}-xyz789.tmp"])
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        n for n, gone in files.items() if not gone)


def test_sweep_restores_a_folder_output_cut_between_its_two_renames(tmp_path):
    out = tmp_path / "frames"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    old = tmp_path / f".frames.trmd-{dead.pid}-old.tmp"  # the previous output, moved aside
    old.mkdir()
    (old / "000001.png").write_bytes(PREVIOUS)
    new = tmp_path / f".frames.trmd-{dead.pid}-q1w2e3r4.tmp"  # the new one, complete or not
    new.mkdir()
    sweep_stale_temps(out)
    assert (out / "000001.png").read_bytes() == PREVIOUS
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames"]


def test_an_interrupt_lost_in_a_finaliser_reaches_the_main_thread_after_the_hook():
    # CPython prints and drops exceptions raised inside sys.unraisablehook, so the hook must
    # return normally and the interrupt arrive afterwards, where the command can unwind
    import time
    import types

    from trmd_cli.cli import boundary

    hook = types.SimpleNamespace(exc_type=KeyboardInterrupt, exc_value=KeyboardInterrupt(),
                                 exc_traceback=None, err_msg=None, object=None)
    returned = False
    with pytest.raises(KeyboardInterrupt):
        boundary._unraisable(hook)
        returned = True
        for _ in range(200):
            time.sleep(0.01)
    assert returned


@pytest.mark.parametrize("sig,code,word", [(signal.SIGINT, 130, "interrupted"),
                                           (signal.SIGTERM, 143, "terminated")])
def test_training_set_interrupted_while_its_workers_simulate(tmp_path, sig, code, word):
    """`simulate --training-set --workers 2`, signalled as a terminal does (the whole group,
    workers included) once samples are being written: one line, the exit code, no temporary
    file, no worker left. Before, a KeyboardInterrupt landed in HDF5's calls into the file
    object (SIGSEGV, or exit 134) or in a worker sending a sample (the parent then waited for
    ever), and the temporary file stayed."""
    from tests.helpers.data import texture
    from trmd_cli.write import write_image

    images = tmp_path / "images"
    images.mkdir()
    write_image(images / "a.png", texture(120, 160, seed=1))
    out = tmp_path / "train.h5"
    proc = launch("simulate", str(images), "--training-set", "-o", str(out), "--count", "100000",
                  "--crop", "64", "--workers", "2", new_session=True)

    def writing() -> bool:
        left = temps(tmp_path)
        return bool(left) and (tmp_path / left[0]).stat().st_size > 100_000

    try:
        wait_until(proc, writing, "samples were being written")
        os.killpg(proc.pid, sig)
        err = finish(proc, timeout=60)
        gone = group_gone(proc.pid)  # (the workers' last moments may outlast the parent)
    finally:  # a run that did not stop must not go on simulating its 100,000 samples
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == code, err
    assert word in one_line(err)
    assert temps(tmp_path) == [] and not out.exists()
    assert gone, "a process of the run outlived it by 10 s"
