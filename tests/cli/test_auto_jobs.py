"""`--jobs auto` (the default of deblur and hfr): how many worker processes a run gets, and that
a run that takes them writes what one process writes."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

import trmd_cli.batch as batch
from tests.cli.test_interrupt_deblur import write_recording
from tests.cli.test_shard_deblur import assert_same, no_stage
from trmd_cli.batch import (
    AUTO_MAX_JOBS,
    AUTO_MIN_WORK,
    AUTO_WORKER_BYTES,
    Ranks,
    ShareReport,
    auto_jobs,
    choose_jobs,
    count_work,
)
from trmd_cli.cli.app import app
from trmd_cli.cli.options import parse_jobs
from trmd_cli.errors import InputError
from trmd_cli.methods import MethodConfig
from trmd_cli.read.base import ReadOptions

runner = CliRunner()
ONE = Ranks()


DAVIS = 346 * 260


@pytest.mark.parametrize("method, frames, threads, cores, free, expected", [
    ("motion", 8, None, 2, None, 2),            # 4 frames each: both cores
    ("motion", 7, None, 2, None, 1),            # too few to pay for a second worker's start
    ("fused", 100, None, 4, None, 4),           # one per core
    ("fused", 100, 2, 8, None, 4),              # --threads 2: one per two cores
    ("motion", 1000, None, 64, None, AUTO_MAX_JOBS),
    ("motion", 1000, None, 8, 3 * AUTO_WORKER_BYTES + 1, 3),   # what free memory holds
    ("motion", 1000, None, 8, AUTO_WORKER_BYTES // 2, 1),      # never fewer than one
    ("motion", 1000, None, 1, None, 1),         # one core
    ("edi", 1000, None, 8, None, 1),            # fast frames: the workers' start would cost more
    ("trmd", 1000, None, 8, None, 1),           # its network keeps every core busy already
])
def test_auto_jobs(method, frames, threads, cores, free, expected):
    assert auto_jobs(method, frames * DAVIS, threads, cores=cores, free_bytes=free) == expected


def test_auto_needs_its_work_per_worker():
    assert AUTO_MIN_WORK == 4 * DAVIS
    assert auto_jobs("motion", 3 * AUTO_MIN_WORK - 1, cores=8) == 2
    assert auto_jobs("motion", 3 * AUTO_MIN_WORK, cores=8) == 3
    # small frames: many more of them per worker (64×48: 117 frames each)
    assert auto_jobs("motion", 200 * 64 * 48, cores=8) == 1
    assert auto_jobs("motion", 300 * 64 * 48, cores=8) == 2


def _never() -> int:
    raise AssertionError("the frames were counted where they do not matter")


def test_choose_jobs_counts_only_when_it_matters():
    motion = MethodConfig("motion")
    assert choose_jobs(3, motion, _never, ranks=ONE) == 3          # --jobs 3 as given
    assert choose_jobs(None, MethodConfig("edi"), _never, ranks=ONE) == 1
    assert choose_jobs(None, motion, _never, ranks=ONE, in_order=True) == 1   # --video
    torchrun = Ranks(rank=0, world=2, local_world=2)
    assert choose_jobs(None, motion, _never, ranks=torchrun) == 1
    assert choose_jobs(None, motion, lambda: 0, ranks=ONE) == 1   # one image
    assert choose_jobs(None, motion, lambda: 2 * AUTO_MIN_WORK, ranks=ONE) == min(
        2, batch.usable_cores())


@pytest.mark.parametrize("text, expected", [("auto", None), ("AUTO", None), ("3", 3),
                                            (" 1 ", 1)])
def test_parse_jobs(text, expected):
    assert parse_jobs(text) == expected


@pytest.mark.parametrize("text, message", [("0", "at least 1"), ("-2", "at least 1"),
                                           ("two", "a whole number or auto"),
                                           ("1.5", "a whole number or auto")])
def test_parse_jobs_refuses(text, message):
    with pytest.raises(InputError, match=message):
        parse_jobs(text)


def test_count_work(tmp_path):
    a = write_recording(tmp_path / "a.h5", 5)
    b = write_recording(tmp_path / "b.h5", 3)
    assert count_work([a], None, ReadOptions()) == 5 * 64 * 48
    assert count_work([a, b], [a, b], ReadOptions()) == 8 * 64 * 48
    # a blurry image and its events: one frame, nothing to share out; the files not read
    image, events = tmp_path / "x.png", tmp_path / "e.npz"
    image.write_bytes(b"not read")
    events.write_bytes(b"not read")
    assert count_work([image, events], None, ReadOptions()) == 0


def test_binned_events_count_no_work(tmp_path):
    """Binned events have no event times: the motion methods give TRMD's or EDI's frames
    there, cheaper than a worker's start."""
    import numpy as np

    from tests.helpers.bins import write_bins
    from trmd_cli.write import write_image

    (tmp_path / "blurry").mkdir()
    for k in range(10):
        write_image(tmp_path / "blurry" / f"{k:04d}.png", np.full((24, 32), 0.5, np.float32))
    bins = write_bins(tmp_path / "event_bins.npz", np.ones((10, 6, 24, 32), np.int32))
    assert count_work([tmp_path / "blurry", bins], None, ReadOptions()) == 0


def test_warnings_in_frame_order_whichever_worker_made_them():
    first = ShareReport(2, (((0, 0), "frame 0: a"), ((0, 2), "frame 2: c")))
    second = ShareReport(1, (((0, 1), "frame 1: b"), ((0, 1), "frame 1: b2")))
    assert batch._said([first, second]) == ["frame 0: a", "frame 1: b", "frame 1: b2",
                                            "frame 2: c"]


@pytest.mark.parametrize("command", ["deblur", "hfr"])
def test_default_run_takes_workers_and_equals_one_process(tmp_path, monkeypatch, command):
    """8 frames of `--method motion` on two cores (as much work as 8 frames of a DAVIS346:
    the minimum made small for the test): two workers of one thread each, and the same files
    as `--jobs 1` (the method's arithmetic does not depend on the thread count)."""
    rec = write_recording(tmp_path / "a.h5", 8)
    monkeypatch.setattr(batch, "AUTO_MIN_WORK", 4 * 64 * 48)
    monkeypatch.setattr(batch, "usable_cores", lambda: 2)
    monkeypatch.setattr(batch, "free_memory_bytes", lambda: None)
    pools = []
    run_pool = batch.run_pool

    def spy(plan, stage, units, jobs, *args, **kwargs):
        pools.append(jobs)
        return run_pool(plan, stage, units, jobs, *args, **kwargs)

    monkeypatch.setattr(batch, "run_pool", spy)
    common = ["--method", "motion", "--contrast", "0.2"]
    one, auto = tmp_path / "one", tmp_path / "auto"
    r = runner.invoke(app, [command, str(rec), "-o", str(one), *common, "--jobs", "1"])
    assert r.exit_code == 0, r.output
    assert pools == []
    r = runner.invoke(app, [command, str(rec), "-o", str(auto), *common])
    assert r.exit_code == 0, r.output
    assert pools == [2]
    assert_same(one, auto)
    no_stage(auto)


def test_no_worker_processes_here_runs_in_this_one(tmp_path, monkeypatch):
    """Where processes cannot be started (no semaphores: a sandbox without /dev/shm), the run
    says so in one warning and makes every frame in this process: the same files."""
    import multiprocessing

    rec = write_recording(tmp_path / "a.h5", 4)

    class NoSemaphores:
        def Queue(self):  # noqa: N802 - multiprocessing's name
            raise OSError(38, "Function not implemented")

    monkeypatch.setattr(multiprocessing, "get_context", lambda method=None: NoSemaphores())
    common = ["--method", "motion", "--contrast", "0.2", "--threads", "1"]
    one, two = tmp_path / "one", tmp_path / "two"
    r = runner.invoke(app, ["deblur", str(rec), "-o", str(one), *common, "--jobs", "1"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["deblur", str(rec), "-o", str(two), *common, "--jobs", "2"])
    assert r.exit_code == 0, r.output
    assert "could not start 2 worker processes ([Errno 38] Function not implemented): the " \
        "work was done in this one" in r.output
    assert_same(one, two)
    no_stage(two)
