"""A second interpreter for work the motion method can do ahead: numpy on a second core.

Contrast maximisation and the tiles' votes are numpy code whose calls hold the interpreter
(``np.bincount``, many small arrays), so a thread beside them does not run in parallel; another
process does. The motion method asks here for what does not depend on its global estimate (the
tiles' votes and the background's motion) before it makes that estimate.

One helper per process, started by :func:`start` when the process has two threads or more
(:func:`~trmd_cli.threads.product_threads`; a ``--jobs`` worker of one thread has none). It is
``python -c`` importing the motion modules only (about 0.4 s, no torch), in a session of its
own (a terminal's Ctrl-C reaches the parent alone), with one thread; it speaks pickles over its
standard input and output and ends when its input closes (the parent ended or stopped it).

The numbers never depend on it: a job is the same pure function on the same inputs, and one the
helper has not begun when its result is wanted (not ready yet, busy, or gone) is computed in the
caller instead and cancelled there. The caller therefore never waits for the helper longer than
the job's own remaining time.
"""

from __future__ import annotations

import atexit
import collections
import os
import pickle
import subprocess
import sys
import threading
from collections.abc import Callable
from typing import Any

from .threads import product_threads

__all__ = ["Ahead", "ahead", "allow", "start", "stop", "running"]

_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
#: what the helper imports before it says it is ready
_IMPORTS = ("numpy", "trmd_cli.motion.tiles")


class _Helper:
    """The parent's end: the process, and a thread reading its messages."""

    def __init__(self) -> None:
        env = {**os.environ, **{k: "1" for k in _THREAD_VARS}}
        code = (f"import sys; sys.path[:0] = {[p for p in sys.path if p]!r}; "
                "from trmd_cli.helper_process import serve; serve()")
        self.proc = subprocess.Popen(
            [sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL, env=env, close_fds=True,
            start_new_session=os.name == "posix")
        self.pid = os.getpid()
        self._cond = threading.Condition()
        self._sending = threading.Lock()
        self.ready = False
        self.alive = True
        self._next = 0
        self._wanted: set[int] = set()
        self._started: set[int] = set()
        self._ended: set[int] = set()  # answered every part, failed, or stopped early
        self._parts: dict[tuple[int, int], Any] = {}
        self._reader = threading.Thread(target=self._read, name="trmd-helper-reader",
                                        daemon=True)
        self._reader.start()

    def _read(self) -> None:
        out = self.proc.stdout
        try:
            while True:
                msg = pickle.load(out)
                with self._cond:
                    kind = msg[0]
                    if kind == "ready":
                        self.ready = True
                    elif msg[1] in self._wanted:
                        if kind == "started":
                            self._started.add(msg[1])
                        elif kind == "part":
                            self._parts[(msg[1], msg[2])] = msg[3]
                        else:  # "end"
                            self._ended.add(msg[1])
                    self._cond.notify_all()
        except BaseException:  # noqa: BLE001 - any end of the pipe: the helper is gone
            with self._cond:
                self.alive = False
                self._cond.notify_all()

    def _send(self, msg) -> bool:
        try:
            with self._sending:
                pickle.dump(msg, self.proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
                self.proc.stdin.flush()
            return True
        except (OSError, ValueError, pickle.PicklingError, AttributeError, TypeError):
            with self._cond:
                self.alive = False
            return False

    def submit(self, fn, args) -> int | None:
        with self._cond:
            # one not ready yet takes the job when it is, if the caller has not done it by then
            if not self.alive:
                return None
            job = self._next
            self._next += 1
            self._wanted.add(job)
        if self._send(("job", job, fn, args)):
            return job
        with self._cond:
            self._forget(job)
        return None

    def take(self, job: int, part: int) -> tuple[bool, Any]:
        """``(True, value)`` once the helper has given that part of a job it began;
        ``(False, None)`` when it has not begun the job (the job is then cancelled), or it
        ended without that part (failed, or gone)."""
        with self._cond:
            if job not in self._wanted:
                return False, None
            if job not in self._started:
                self._forget(job)
                cancel = self.alive
            else:
                key = (job, part)
                while key not in self._parts and job not in self._ended and self.alive:
                    self._cond.wait()
                return (True, self._parts[key]) if key in self._parts else (False, None)
        if cancel:
            self._send(("cancel", job))
        return False, None

    def drop(self, job: int) -> None:
        """The job is not wanted any more: the helper skips it, or stops it after the part it
        is on."""
        with self._cond:
            cancel = self.alive and job in self._wanted and job not in self._ended
            self._forget(job)
        if cancel:
            self._send(("cancel", job))

    def _forget(self, job: int) -> None:
        self._wanted.discard(job)
        self._started.discard(job)
        self._ended.discard(job)
        for key in [k for k in self._parts if k[0] == job]:
            del self._parts[key]

    def close(self) -> None:
        # it holds nothing worth finishing: a job it is on would only delay this process's exit
        self.proc.kill()
        self.proc.wait()
        for pipe in (self.proc.stdin, self.proc.stdout):
            try:
                pipe.close()
            except OSError:
                pass


_HELPER: list[_Helper] = []
_ALLOWED = [True]


def allow(on: bool) -> None:
    """Whether this process may start a helper (default: yes); ``False`` also stops the one
    running. The numbers are the same either way: for timing one against the other."""
    _ALLOWED[0] = bool(on)
    if not on:
        stop()


def start() -> bool:
    """Start this process's helper unless it runs already, the process has one thread or
    :func:`allow` said no; returns whether one runs (or starts). Returns at once: the helper
    says when it is ready."""
    if not _ALLOWED[0] or product_threads() < 2:
        return False
    helper = _current()
    if helper is not None:
        return helper.alive
    try:
        helper = _Helper()
    except OSError:
        return False
    _HELPER[:] = [helper]
    return True


def running() -> bool:
    """Whether this process's helper is ready for work."""
    helper = _current()
    return helper is not None and helper.alive and helper.ready


def stop() -> None:
    """End this process's helper (at exit, or to start afresh)."""
    helper = _current()
    _HELPER.clear()
    if helper is not None:
        helper.close()


def _current() -> _Helper | None:
    # a forked child does not own its parent's helper
    return _HELPER[0] if _HELPER and _HELPER[0].pid == os.getpid() else None


atexit.register(stop)


class Ahead:
    """The parts of ``fn(*args)`` (a generator's items, or a function's one value), begun in
    the helper when one is ready; the caller asks for each part with :meth:`take` and computes
    what the helper did not give. Call :meth:`drop` when done with it."""

    def __init__(self, fn: Callable, args: tuple) -> None:
        self._fn, self._args = fn, args
        helper = _current()
        self._helper = helper
        self._job = None if helper is None else helper.submit(fn, args)

    @property
    def in_helper(self) -> bool:
        """Whether the helper holds the job (it may not have begun it)."""
        return self._job is not None

    def take(self, part: int = 0) -> tuple[bool, Any]:
        """``(True, value)``: part ``part`` from the helper, waited for if it began the job;
        ``(False, None)``: it has not begun it (then cancelled: ask no further part), or ended
        without that part."""
        if self._job is None:
            return False, None
        ok, value = self._helper.take(self._job, part)
        if not ok:
            self.drop()
        return ok, value

    def result(self) -> Any:
        """A plain function's value: the helper's if it began the job, else computed here
        now (its errors raised here, as the call's)."""
        ok, value = self.take(0)
        self.drop()
        return value if ok else self._fn(*self._args)

    def drop(self) -> None:
        """No further part is wanted: the helper skips the job, or stops after its part."""
        if self._job is not None:
            job, self._job = self._job, None
            self._helper.drop(job)


def ahead(fn: Callable, *args) -> Ahead:
    """``fn(*args)`` begun in this process's helper when one is ready (``fn`` a module-level
    function, a generator function for a job of several parts; ``args`` picklable); see
    :class:`Ahead`."""
    return Ahead(fn, args)


# --------------------------------------------------------------------------------------------
# The helper's side


def serve() -> None:
    """The helper's loop: jobs from standard input in order, cancelled ones skipped, each
    answered on standard output; returns when the input closes."""
    import inspect
    import signal

    from .heap import tune_memory

    tune_memory()  # as the parent's: a job's temporaries are reused, not mapped anew
    if hasattr(signal, "SIGINT"):
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    src = os.fdopen(os.dup(0), "rb")
    out = os.fdopen(os.dup(1), "wb")
    # nothing the jobs print may reach the pipe
    devnull = os.open(os.devnull, os.O_RDWR)
    os.dup2(devnull, 0)
    os.dup2(devnull, 1)
    import importlib

    for name in _IMPORTS:
        importlib.import_module(name)
    try:
        import cv2

        cv2.setNumThreads(1)
    except ImportError:
        pass

    jobs: collections.deque = collections.deque()
    cancelled: set[int] = set()
    cond = threading.Condition()
    closed = [False]

    def read() -> None:
        try:
            while True:
                msg = pickle.load(src)
                with cond:
                    if msg[0] == "cancel":
                        cancelled.add(msg[1])
                    else:
                        jobs.append(msg)
                    cond.notify()
        except BaseException:  # noqa: BLE001 - the parent closed its end, or went
            with cond:
                closed[0] = True
                cond.notify()

    threading.Thread(target=read, daemon=True).start()

    def say(msg) -> None:
        pickle.dump(msg, out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()

    try:
        say(("ready",))
        while True:
            with cond:
                while not jobs and not closed[0]:
                    cond.wait()
                if not jobs:
                    return
                _, job, fn, args = jobs.popleft()
                if job in cancelled:
                    cancelled.discard(job)
                    continue
                say(("started", job))
            try:
                value = fn(*args)
                parts = value if inspect.isgenerator(value) else iter((value,))
                for k, item in enumerate(parts):
                    say(("part", job, k, item))
                    with cond:
                        if job in cancelled:
                            break
            except Exception:  # noqa: BLE001 - the caller computes it again and sees the error
                pass
            with cond:
                cancelled.discard(job)
            say(("end", job))
    except (OSError, ValueError):
        return
