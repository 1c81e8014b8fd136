"""The helper process: work begun there gives the caller's own numbers, and anything the helper
has not done (not begun, failed, gone) the caller does."""

from __future__ import annotations

import math
import operator
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from trmd_cli import helper_process
from trmd_cli.motion.tiles import TileEvidence, background_motion, tile_velocities

from .helpers.data import texture
from .motion.test_tiles import H, W, _translated_events


@pytest.fixture
def helper(monkeypatch):
    """This process's helper, started and ready (as in a process of two threads)."""
    monkeypatch.setattr(helper_process, "product_threads", lambda: 2)
    helper_process.stop()
    assert helper_process.start()
    deadline = time.monotonic() + 60
    while not helper_process.running():
        assert time.monotonic() < deadline, "the helper did not get ready"
        time.sleep(0.02)
    yield helper_process._current()
    helper_process.stop()


def _until(cond, what: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, what
        time.sleep(0.01)


def _answered(helper, counter: list) -> None:
    """Count the parts the helper gives (``counter``)."""
    take = helper.take

    def counted(job, part):
        ok, value = take(job, part)
        counter.append(ok)
        return ok, value

    helper.take = counted


def test_tiles_from_the_helper_are_the_callers_own(helper):
    """A background translating (12, −6) px with a patch sliding (−30, 10) on its own: the
    votes and the background's motion the helper gives are exactly those computed here."""
    ev, ex = _translated_events((12.0, -6.0), texture(H, W, seed=2), seed=1,
                                region=(slice(40, 80), slice(40, 120)), other=(-30.0, 10.0))
    expected_votes = tile_velocities(ev, ex)
    expected_bg = background_motion(ev, ex, votes=expected_votes)
    assert expected_bg is not None
    answers: list = []
    _answered(helper, answers)
    tiles = TileEvidence(ev, ex)
    try:
        _until(lambda: tiles._ahead._job in helper._started, "the helper did not begin")
        assert list(tiles.votes().items()) == list(expected_votes.items())
        assert tiles.background() == expected_bg
    finally:
        tiles.drop()
    assert answers == [True, True]


def test_motion_method_frames_are_the_same_with_the_helper(helper):
    """The motion method on a frame with a mover: the same frames bit for bit whether the
    tiles' votes came from the helper or not, and they did come from it."""
    from trmd_cli.methods import MotionMethod

    from .test_deconv import _sample

    s = _sample(4, foreground=True)
    m = MotionMethod(contrast=s.contrast)
    answers: list = []
    _answered(helper, answers)
    with_helper = m(s.blurry, s.events, s.exposure).frames
    assert answers and all(answers)
    helper_process.allow(False)
    try:
        alone = m(s.blurry, s.events, s.exposure).frames
    finally:
        helper_process.allow(True)
    assert np.array_equal(with_helper, alone)


def test_a_job_not_begun_is_done_by_the_caller_and_skipped_there(helper):
    """While the helper sleeps on a first job, two more are wanted: the caller computes the
    one and gives up the other (a sleep of 3 s), which the helper then skips: a fourth job
    begins there at once after the first."""
    busy = helper_process.ahead(time.sleep, 1.0)
    _until(lambda: busy._job in helper._started, "the helper did not begin the first job")
    assert helper_process.ahead(operator.add, 2, 3).result() == 5
    skipped = helper_process.ahead(time.sleep, 3.0)
    assert skipped.in_helper and skipped.take() == (False, None)
    assert busy.take() == (True, None)
    busy.drop()
    since = time.monotonic()
    fourth = helper_process.ahead(os.getpid)
    _until(lambda: fourth._job in helper._started, "the helper did not begin the fourth job")
    assert time.monotonic() - since < 2.0
    assert fourth.result() not in (None, os.getpid())


def test_a_failed_job_raises_the_callers_own_error(helper):
    failing = helper_process.ahead(math.sqrt, -1.0)
    job = failing._job
    _until(lambda: job in helper._ended, "the helper did not end the job")
    with pytest.raises(ValueError, match="math domain error"):
        failing.result()


def test_a_helper_gone_mid_job_leaves_the_job_to_the_caller(helper):
    sleeping = helper_process.ahead(time.sleep, 0.5)
    _until(lambda: sleeping._job in helper._started, "the helper did not begin the job")
    helper.proc.kill()
    start = time.monotonic()
    assert sleeping.result() is None
    assert time.monotonic() - start >= 0.45  # slept here
    assert not helper_process.running()
    # and a later job is the caller's at once
    assert not helper_process.ahead(operator.mul, 6, 7).in_helper


def test_no_helper_on_one_thread_or_when_not_allowed(monkeypatch):
    helper_process.stop()
    monkeypatch.setattr(helper_process, "product_threads", lambda: 1)
    assert not helper_process.start()
    assert not helper_process.ahead(operator.add, 1, 1).in_helper
    monkeypatch.setattr(helper_process, "product_threads", lambda: 2)
    helper_process.allow(False)
    try:
        assert not helper_process.start()
    finally:
        helper_process.allow(True)
    assert helper_process.ahead(operator.add, 1, 1).result() == 2


@pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="reads /proc")
def test_the_helper_ends_with_its_parent():
    """A parent killed outright (no exit handler runs) leaves no helper behind."""
    code = ("import sys, time; from trmd_cli import helper_process as h; "
            "h.product_threads = lambda: 2; h.start(); "
            "print(h._current().proc.pid, flush=True); time.sleep(60)")
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        pid = int(parent.stdout.readline())
        assert _alive(pid)
    finally:
        parent.kill()
        parent.wait()
        parent.stdout.close()
    _until(lambda: not _alive(pid), "the helper outlived its parent", timeout=30)


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, reaped by nobody here, does not)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False
