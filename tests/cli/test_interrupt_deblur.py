"""Interrupted `trmd deblur` (every frame of a recording, with ``--video``) and `trmd hfr` (into
an .mp4, a .gif and a folder): Ctrl-C, ``kill`` and ``kill -9`` leave a previous output
byte-identical and no temporary files (``kill -9`` cannot clean up: its temporaries are swept by
the next run that writes that output).

Real processes (``python -m trmd_cli``) are signalled in the middle of the work: once their
temporary output folder holds a few finished frames, or once the FFmpeg encoder they started is
running. Ctrl-C is sent as a terminal sends it, to the whole process group; FFmpeg, which
imageio-ffmpeg starts in a group of its own, must not be left running either way.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.procs import PREVIOUS, children, finish, temps, wait_until
from tests.helpers.procs import launch as _launch
from trmd_cli.cli.app import app
from trmd_cli.events import Exposure, make_stream
from trmd_cli.write import H5Writer

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="signals and /proc as on Linux")

W, H = 64, 48
runner = CliRunner()


def write_recording(path: Path, frames: int, events_per_frame: int = 800) -> Path:
    """trmd HDF5: a 10 ms exposure every 20 ms, events all the time (the gaps have some)."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:H, 0:W]
    base = (0.2 + 0.6 * (((xx // 8) + (yy // 8)) % 2)).astype(np.float32)
    with H5Writer(path, W, H) as w:
        t = np.concatenate([k * 20_000 + np.sort(rng.integers(0, 20_000, events_per_frame))
                            for k in range(frames)])
        n = len(t)
        w.add_events(make_stream(rng.integers(0, W, n), rng.integers(0, H, n), t,
                                 rng.integers(0, 2, n), W, H))
        for k in range(frames):
            w.add_frame(np.roll(base, k, axis=1), Exposure(k * 20_000 + 5_000, k * 20_000 + 15_000))
    return path


@pytest.fixture(scope="module")
def long_rec(tmp_path_factory) -> Path:
    """1500 frames: deblurring all of them takes seconds, however fast the machine."""
    return write_recording(tmp_path_factory.mktemp("src") / "long.h5", 1500)


@pytest.fixture(scope="module")
def short_rec(tmp_path_factory) -> Path:
    return write_recording(tmp_path_factory.mktemp("src") / "short.h5", 3)


# -- helpers --------------------------------------------------------------------------------------


def launch(*args: str):
    """``trmd ARGS --contrast 0.2`` in a process group of its own, as a shell job."""
    return _launch(*args, "--contrast", "0.2", new_session=True)


def previous_output(path: Path) -> dict[str, bytes]:
    """Put the user's previous output at ``path`` (a file, or a folder of files for a folder
    output) and return its snapshot."""
    if path.suffix:
        path.write_bytes(PREVIOUS)
    else:
        (path / "000000").mkdir(parents=True)
        (path / "meta.json").write_bytes(PREVIOUS)
        (path / "000000" / "sharp.png").write_bytes(PREVIOUS * 3)
    return snapshot(path)


def snapshot(path: Path) -> dict[str, bytes]:
    if path.is_file():
        return {"": path.read_bytes()}
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*"))
            if p.is_file()}


def gone(pid: int) -> bool:
    """The process has exited (a zombie waiting for a dead parent counts as gone)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] in "ZX"
    except OSError:
        return True


def wait_gone(pids: list[int], timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while not all(gone(p) for p in pids):
        assert time.monotonic() < end, f"processes {pids} still running"
        time.sleep(0.02)


def frames_done(folder: Path, out_name: str, at_least: int) -> bool:
    """The run's temporary output folder holds ``at_least`` finished entries."""
    for tmp in folder.glob(f".{out_name}.trmd-*.tmp"):
        try:
            if sum(1 for _ in tmp.iterdir()) >= at_least:
                return True
        except OSError:
            pass
    return False


def one_line(stderr: str) -> str:
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, stderr
    assert "Traceback" not in stderr
    return lines[0]


def stop(proc: subprocess.Popen, sig: signal.Signals) -> str:
    """Deliver ``sig`` as a user would (Ctrl-C: to the whole process group); return stderr."""
    if sig == signal.SIGINT:
        os.killpg(proc.pid, sig)
    else:
        proc.send_signal(sig)
    return finish(proc)


CAUGHT = [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")]


# -- deblur: every frame of a recording, plus a video ---------------------------------------------


@pytest.mark.parametrize("sig,code,word", CAUGHT, ids=["ctrl-c", "kill"])
def test_deblur_interrupted_mid_recording(tmp_path, long_rec, sig, code, word):
    out, video = tmp_path / "out", tmp_path / "latent.mp4"
    before = previous_output(out), previous_output(video)
    proc = launch("deblur", str(long_rec), "-o", str(out), "--video", str(video), "--overwrite")
    wait_until(proc, lambda: frames_done(tmp_path, "out", 3) and children(proc.pid),
               "three frames were written and the encoder started")
    encoder = children(proc.pid)
    err = stop(proc, sig)
    assert proc.returncode == code, err
    assert f"{word}; no partial output was left" in one_line(err)
    assert (snapshot(out), snapshot(video)) == before
    assert temps(tmp_path) == []
    wait_gone(encoder)


@pytest.mark.parametrize("sig,code,word", CAUGHT, ids=["ctrl-c", "kill"])
def test_motion_run_interrupted_leaves_no_helper(tmp_path, long_rec, sig, code, word):
    """The motion method on two threads starts a helper process after its first frame, in a
    session of its own (a terminal's Ctrl-C does not reach it): the run stops it as it
    ends."""
    out = tmp_path / "out"
    before = previous_output(out)
    proc = launch("deblur", str(long_rec), "-o", str(out), "--overwrite", "--method", "motion",
                  "--jobs", "1", "--threads", "2")
    wait_until(proc, lambda: frames_done(tmp_path, "out", 3) and children(proc.pid),
               "three frames were written and the helper started")
    helper = children(proc.pid)
    err = stop(proc, sig)
    assert proc.returncode == code, err
    # (the frames' warnings first: too few random events for a motion)
    assert "Traceback" not in err
    assert err.splitlines()[-1] == f"error: {word}; no partial output was left", err
    assert snapshot(out) == before
    assert temps(tmp_path) == []
    wait_gone(helper)


def test_deblur_killed_leaves_temps_that_the_next_run_sweeps(tmp_path, long_rec, short_rec):
    out, video = tmp_path / "out", tmp_path / "latent.mp4"
    before = previous_output(out), previous_output(video)
    proc = launch("deblur", str(long_rec), "-o", str(out), "--video", str(video), "--overwrite")
    wait_until(proc, lambda: frames_done(tmp_path, "out", 3) and children(proc.pid),
               "three frames were written and the encoder started")
    encoder = children(proc.pid)
    proc.kill()
    finish(proc)
    assert proc.returncode == -signal.SIGKILL
    wait_gone(encoder)  # FFmpeg sees its input end and exits: nothing keeps running
    assert (snapshot(out), snapshot(video)) == before
    left = temps(tmp_path)
    assert any(n.startswith(f".out.trmd-{proc.pid}-") for n in left), left
    assert any(n.startswith(f".latent.mp4.trmd-{proc.pid}-") for n in left), left

    r = runner.invoke(app, ["deblur", str(short_rec), "-o", str(out), "--video", str(video),
                            "--overwrite", "--contrast", "0.2"])
    assert r.exit_code == 0, r.output
    assert temps(tmp_path) == []
    assert sorted(p.name for p in out.iterdir()) == ["meta.json", *(f"short.h5_frame{k}"
                                                                     for k in range(3))]
    assert video.read_bytes()[4:8] == b"ftyp"


# -- hfr: one continuous video (or folder) --------------------------------------------------------


@pytest.mark.parametrize("sig,code,word", CAUGHT, ids=["ctrl-c", "kill"])
@pytest.mark.parametrize("out_name", ["slowmo.mp4", "slowmo.gif", "slowmo"])
def test_hfr_interrupted(tmp_path, long_rec, out_name, sig, code, word):
    out = tmp_path / out_name
    before = previous_output(out)
    proc = launch("hfr", str(long_rec), "-o", str(out), "--overwrite", "--jobs", "1")
    if out_name.endswith(".mp4"):
        ready = lambda: bool(temps(tmp_path)) and bool(children(proc.pid))  # noqa: E731
        what = "the encoder started"
    elif out_name.endswith(".gif"):
        # its temporary file is made just before the first frame; frames are then gathered in
        # memory until the end, so nothing outside shows how far it got
        ready = lambda: bool(temps(tmp_path)) and _sleep(0.3)  # noqa: E731
        what = "the first frames were made"
    else:
        ready = lambda: frames_done(tmp_path, out_name, 20)  # noqa: E731
        what = "20 frames were written"
    wait_until(proc, ready, what)
    encoder = children(proc.pid)
    err = stop(proc, sig)
    assert proc.returncode == code, err
    assert f"{word}; no partial output was left" in one_line(err)
    assert snapshot(out) == before
    assert temps(tmp_path) == []
    wait_gone(encoder)


def test_hfr_mp4_killed_leaves_a_temp_that_the_next_run_sweeps(tmp_path, long_rec, short_rec):
    out = tmp_path / "slowmo.mp4"
    before = previous_output(out)
    proc = launch("hfr", str(long_rec), "-o", str(out), "--overwrite", "--jobs", "1")
    wait_until(proc, lambda: bool(temps(tmp_path)) and bool(children(proc.pid)),
               "the encoder started")
    encoder = children(proc.pid)
    proc.kill()
    finish(proc)
    wait_gone(encoder)
    assert snapshot(out) == before
    left = temps(tmp_path)
    assert left and all(n.startswith(f".slowmo.mp4.trmd-{proc.pid}-") for n in left), left

    r = runner.invoke(app, ["hfr", str(short_rec), "-o", str(out), "--overwrite",
                            "--contrast", "0.2"])
    assert r.exit_code == 0, r.output
    assert temps(tmp_path) == []
    assert out.read_bytes()[4:8] == b"ftyp"


def _sleep(seconds: float) -> bool:
    time.sleep(seconds)
    return True


@pytest.mark.skipif(not hasattr(signal, "SIGUSR1"), reason="no SIGUSR1 here")
def test_sigusr1_prints_every_threads_stack_and_the_run_goes_on(tmp_path, long_rec):
    """``kill -USR1`` on a run that seems stuck: its threads' stacks on stderr (the frame
    loop's included), and it goes on writing frames; Ctrl-C then ends it as usual (every
    frame in order in one process, as ``--video`` makes it)."""
    out = tmp_path / "out"
    proc = launch("deblur", str(long_rec), "-o", str(out), "--video", str(tmp_path / "a.mp4"))
    wait_until(proc, lambda: frames_done(tmp_path, "out", 3), "three frames were written")
    proc.send_signal(signal.SIGUSR1)
    time.sleep(0.5)
    assert proc.poll() is None
    done = sum(1 for tmp in tmp_path.glob(".out.trmd-*.tmp") for _ in tmp.iterdir())
    wait_until(proc, lambda: frames_done(tmp_path, "out", done + 3), "three more frames")
    err = stop(proc, signal.SIGINT)
    assert proc.returncode == 130, err
    assert "Thread 0x" in err and "deblur.py" in err, err
    assert err.splitlines()[-1] == "error: interrupted; no partial output was left", err
    assert temps(tmp_path) == []
