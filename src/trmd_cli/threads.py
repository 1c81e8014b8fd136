"""The process's worker threads for the weight-free methods: sparse products split by rows,
and work run beside the caller.

SciPy's CSR product runs on one core and releases the interpreter while it runs, so a matrix
cut into blocks of rows is multiplied on several threads at once: each row's sum is the same
sum in the same order as in one product, so the result is identical whatever the thread count.
The deconvolution's blur operator (:class:`~trmd_cli.deconv.BlurOperator`) spends most of its
time in such products and in building its matrix, which is split the same way.

How many threads: torch's count, which ``--threads`` and ``--jobs`` set for the process
(:func:`product_threads`); with one, everything runs in the caller, in the same order. The
pool's tasks never wait on the pool themselves (no deadlock); work run :func:`beside` the
caller has a thread of its own.
"""

from __future__ import annotations

import os
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .signals import shielded

__all__ = ["RowBlocks", "product_threads", "set_threads", "usable_cores", "run_split",
           "map_shared", "beside"]

#: fewer stored entries than this: one product, no threads (their hand-off would cost more)
MIN_SPLIT_NNZ = 200_000

_POOLS: dict[tuple[int, int], ThreadPoolExecutor] = {}
_SIDE: dict[tuple[int, str], ThreadPoolExecutor] = {}


def set_threads(count: int) -> None:
    """The process's thread count (``--threads``): torch's when torch is loaded; otherwise
    ``OMP_NUM_THREADS``, which torch takes as its count when it is imported and
    :func:`product_threads` reads until then, so a method without weights (EDI) is not made
    to import torch (a second) to be told its count."""
    if count < 1:
        from .errors import InputError

        raise InputError(f"threads must be ≥ 1, got {count}")
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(count)
    else:
        os.environ["OMP_NUM_THREADS"] = str(count)


def product_threads() -> int:
    """Threads for one product: torch's thread count (what ``--threads`` and ``--jobs`` set for
    this process), at most 4 (a product takes a few milliseconds; finer parts cost their
    hand-offs, and more than two were not measured). A process that has not loaded torch
    (reading events alone) is not made to load it (a second's import): it counts the cores it
    may run on, or ``OMP_NUM_THREADS`` where set (a ``--jobs`` worker's): torch's own
    default."""
    torch = sys.modules.get("torch")
    if torch is not None:
        count = int(torch.get_num_threads())
    else:
        try:
            count = int(os.environ.get("OMP_NUM_THREADS", ""))
        except ValueError:
            count = usable_cores()
    return max(1, min(count, 4))


def usable_cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else \
        (os.cpu_count() or 1)


def _pool(threads: int) -> ThreadPoolExecutor:
    """A pool kept for the process (by process id: a forked worker does not inherit its
    parent's threads, only their record)."""
    key = (os.getpid(), threads)
    if key not in _POOLS:
        _POOLS[key] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="trmd-sparse")
    return _POOLS[key]


def run_split(part, parts: int) -> list:
    """``[part(0), …, part(parts − 1)]``, the first in the calling thread and the others on the
    process's pool; every part has ended before this returns or raises."""
    if parts <= 1:
        return [part(0)]
    # a Ctrl-C is held while the pool's locks are taken (see trmd_cli.signals.shielded)
    with shielded():
        futures = [_pool(parts).submit(part, k) for k in range(1, parts)]
    try:
        first = part(0)
    finally:
        with shielded():
            done = [f.exception() for f in futures]  # waits for each
    for e in done:
        if e is not None:
            raise e
    return [first] + [f.result() for f in futures]


def map_shared(fn, items) -> list:
    """``[fn(x) for x in items]``, the items shared out over :func:`product_threads` threads
    (every n-th to each, so neighbours of similar cost go to different threads), the results
    in the items' order."""
    items = list(items)
    parts = max(min(product_threads(), len(items)), 1)
    shares = run_split(lambda p: [fn(x) for x in items[p::parts]], parts)
    return [shares[i % parts][i // parts] for i in range(len(items))]


class _Done:
    """A finished call's outcome, with a future's ``result()``."""

    def __init__(self, fn, args) -> None:
        try:
            self._value, self._error = fn(*args), None
        except Exception as e:  # noqa: BLE001 - raised again by result(), as a future would
            self._value, self._error = None, e

    def result(self):
        if self._error is not None:
            raise self._error
        return self._value


def beside(fn, *args, lane: str = "side"):
    """``fn(*args)`` on a thread of its own while the caller goes on, when this process has two
    threads or more (:func:`product_threads`); else called now. Returns an object whose
    ``result()`` gives its value or raises its error. Calls in one ``lane`` run one after the
    other on its thread; another lane (e.g. a network's frames, while the caller's own work
    puts smaller jobs beside it) has a thread of its own."""
    if product_threads() < 2:
        return _Done(fn, args)
    key = (os.getpid(), lane)
    if key not in _SIDE:
        _SIDE[key] = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"trmd-beside-{lane}")
    with shielded():
        return _Later(_SIDE[key].submit(fn, *args))


class _Later:
    """A call on a lane's thread; ``result()`` waits for it with a Ctrl-C held until it
    returns (:func:`~trmd_cli.signals.shielded`: raised inside the future's lock, it left the
    lock held and the lane's thread, which must take it to finish, waited for ever)."""

    def __init__(self, future) -> None:
        self._future = future

    def result(self):
        with shielded():
            return self._future.result()


class RowBlocks:
    """A CSR matrix as ``parts`` blocks of consecutive rows with about equal stored entries.

    Args:
        matrix: (R, C) ``scipy.sparse`` CSR matrix.
        parts: number of blocks (None: :func:`product_threads`); 1 for a small matrix.
    """

    def __init__(self, matrix, parts: int | None = None) -> None:
        self.matrix = matrix
        self.shape = matrix.shape
        parts = product_threads() if parts is None else max(int(parts), 1)
        if matrix.nnz < MIN_SPLIT_NNZ:
            parts = 1
        indptr = matrix.indptr
        # row boundaries where the running count of entries crosses each share
        cuts = np.searchsorted(indptr, np.linspace(0, matrix.nnz, parts + 1)[1:-1])
        bounds = np.unique(np.concatenate([[0], cuts, [matrix.shape[0]]]))
        self.rows = [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
        self.blocks = [_rows(matrix, a, b) for a, b in self.rows] if len(self.rows) > 1 \
            else [matrix]

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        """``matrix @ x`` for a (C,) or (C, K) array."""
        if len(self.blocks) == 1:
            return self.matrix @ x
        out = np.empty((self.shape[0],) + x.shape[1:], np.result_type(self.matrix.dtype, x))

        def one(k: int) -> None:
            a, b = self.rows[k]
            out[a:b] = self.blocks[k] @ x

        run_split(one, len(self.blocks))
        return out


def _rows(matrix, first: int, stop: int):
    """Rows ``first`` to ``stop`` of a CSR matrix as a CSR matrix on views of its arrays
    (slicing copies them, and so does SciPy's constructor for views of a larger array)."""
    import scipy.sparse as sp

    ptr = matrix.indptr[first:stop + 1]
    a, b = int(ptr[0]), int(ptr[-1])
    out = sp.csr_matrix((stop - first, matrix.shape[1]), dtype=matrix.dtype)
    out.data, out.indices, out.indptr = matrix.data[a:b], matrix.indices[a:b], ptr - a
    out.has_sorted_indices = matrix.has_sorted_indices
    return out
