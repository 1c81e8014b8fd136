"""Ctrl-C and ``kill`` as exceptions that cannot be lost on the way to the writers.

Python turns SIGINT into :class:`KeyboardInterrupt` at whatever bytecode runs next. A few places
in the standard library and in C extensions call Python code and then *clear* any exception it
raised: ``io.BufferedWriter(raw)`` asks ``raw.tell()`` and drops its error, IOBase finalisers drop
the errors of ``close()``. An interrupt landing there vanishes and the run would finish and
commit its output as if nothing had happened.

So while :func:`handled` is active, the handlers also *record* the signal, and
:func:`raise_if_received` raises it again at the points that matter: before a writer commits an
output (:mod:`trmd_cli.write` calls it before every rename) and after the known swallowing
calls. Outside :func:`handled` (the package used as a library) Python's defaults are untouched.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

__all__ = ["Terminated", "handled", "raise_if_received", "deferred", "recorded_only",
           "shielded", "stacks_on_request"]


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so ``with`` blocks (atomic writers) clean up."""


def _exception(signum: int) -> KeyboardInterrupt:
    return Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


#: > 0 while :func:`recorded_only` is active: the handlers record, and do not raise
_holding: list[int] = [0]
#: every signal received while :func:`handled` is active, in order (empty: none yet)
_received: list[int] = []


def _on_signal(signum, frame) -> None:
    _received.append(signum)
    if _holding[0]:
        return
    raise _exception(signum)


@contextlib.contextmanager
def recorded_only() -> Iterator[None]:
    """While active, a signal is only recorded (:func:`raise_if_received` raises it).

    For code that C calls back into at moments no Python code chooses: HDF5 calls a file
    object's ``seek`` and ``write`` even when h5py frees an object, and a KeyboardInterrupt
    raised there (on the callback's first line, before any ``try``) made h5py die with SIGSEGV.
    Blocking the signals cannot prevent it: the kernel hands a process's signal to any thread
    that does not block it (a pool's, a progress bar's), and Python then runs the handler in
    the main thread whatever that thread blocks."""
    _holding[0] += 1
    try:
        yield
    finally:
        _holding[0] -= 1


@contextlib.contextmanager
def shielded() -> Iterator[None]:
    """Run a call that takes a lock (a queue's ``get`` or ``put``) with Ctrl-C and ``kill``
    recorded, and raise one received meanwhile as it returns (main thread only; elsewhere, or
    outside :func:`handled`, a no-op).

    Python raises KeyboardInterrupt at whatever bytecode runs next, which may be inside the
    ``__enter__`` of a ``with lock:`` after the lock was taken and before the ``with`` owns
    it: the lock stays held. The next call that takes it then waits for ever — the cleanup's
    own ``put`` of the same queue (a ``--jobs`` worker told to stop), or the frame producer
    a Ctrl-C'd consumer joins (``overlap.ahead``): runs that did not end after their signal.
    A blocked call is not interrupted: it returns as it would have (the producer's next
    item), and the signal is raised then."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    seen = len(_received)
    with recorded_only():
        yield
    if len(_received) > seen:
        raise _exception(_received[seen])


def raise_if_received() -> None:
    """Raise the interrupt received earlier (if any), even if something swallowed it then."""
    if _received:
        raise _exception(_received[0])


@contextlib.contextmanager
def handled() -> Iterator[None]:
    """Install the recording handlers for SIGINT and SIGTERM (main thread only; elsewhere a
    no-op). Python's default for SIGTERM is to die on the spot, skipping every cleanup; here it
    raises :class:`Terminated` instead. SIGUSR1, where there is one, prints every thread's
    stack on stderr and the run goes on (:func:`stacks_on_request`)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _received.clear()
    previous = {s: signal.signal(s, _on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        with stacks_on_request():
            yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        _received.clear()


@contextlib.contextmanager
def stacks_on_request() -> Iterator[None]:
    """While active, ``kill -USR1 PID`` prints the Python stack of every thread of the process
    on stderr, and the process goes on: to see where a run that seems stuck is. A no-op where
    there is no SIGUSR1 or stderr is no file (a captured stream)."""
    import faulthandler
    import sys

    usr1 = getattr(signal, "SIGUSR1", None)
    try:
        if usr1 is None or sys.__stderr__ is None:
            raise ValueError
        faulthandler.register(usr1, file=sys.__stderr__, all_threads=True)
    except (ValueError, OSError, AttributeError, RuntimeError):
        yield
        return
    try:
        yield
    finally:
        faulthandler.unregister(usr1)


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Hold SIGINT/SIGTERM while a temporary file is created and named: Python runs the handler
    (KeyboardInterrupt) at the first bytecode after unblocking, i.e. inside the cleanup's try."""
    mask = getattr(signal, "pthread_sigmask", None)
    if mask is None or threading.current_thread() is not threading.main_thread():
        yield
        return
    sigs = {signal.SIGINT, signal.SIGTERM}
    old = mask(signal.SIG_BLOCK, sigs)
    try:
        yield
    finally:
        mask(signal.SIG_SETMASK, old)
