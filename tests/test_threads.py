"""Products split by rows over threads give the one-thread numbers exactly; parts all end
before a result or an error comes back; the blur matrix built in bands is the one-band one."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from trmd_cli import threads
from trmd_cli.deconv import BlurOperator, deconvolve
from trmd_cli.motion import GlobalMotion
from trmd_cli.threads import RowBlocks, beside, run_split


@pytest.fixture
def torch_threads():
    """Sets torch's thread count for one test (what ``--threads`` does), then restores it."""
    before = torch.get_num_threads()
    yield torch.set_num_threads
    torch.set_num_threads(before)


def _matrix(rows: int, cols: int, seed: int = 0) -> sp.csr_matrix:
    rng = np.random.default_rng(seed)
    # uneven rows (some empty) so that blocks of equal entries are not blocks of equal rows
    m = sp.random(rows, cols, density=0.02, random_state=rng, format="csr", dtype=np.float32)
    keep = np.where(rng.random((rows, 1)) < 0.3, 0.0, 1.0)
    keep[rows // 2] = 0.0
    m = m.multiply(keep).tocsr()
    m.eliminate_zeros()
    return sp.csr_matrix(m, dtype=np.float32)


@pytest.mark.parametrize("parts", [1, 2, 3, 4])
@pytest.mark.parametrize("width", [None, 3])
def test_split_product_is_the_product_bit_for_bit(parts, width, monkeypatch):
    m = _matrix(3000, 2000)
    monkeypatch.setattr(threads, "MIN_SPLIT_NNZ", 0)  # split even this small matrix
    blocks = RowBlocks(m, parts)
    assert len(blocks.blocks) == parts
    # the blocks cover the rows once, in order, and hold about equal shares of the entries
    assert blocks.rows[0][0] == 0 and blocks.rows[-1][1] == m.shape[0]
    assert all(a[1] == b[0] for a, b in zip(blocks.rows[:-1], blocks.rows[1:]))
    counts = [b.nnz for b in blocks.blocks]
    assert sum(counts) == m.nnz and max(counts) - min(counts) <= 0.05 * m.nnz
    x = np.random.default_rng(1).random(m.shape[1] if width is None else (m.shape[1], width))
    x = x.astype(np.float32)
    assert np.array_equal(blocks @ x, m @ x)


def test_blocks_are_views_of_the_matrix(monkeypatch):
    m = _matrix(1000, 800)
    monkeypatch.setattr(threads, "MIN_SPLIT_NNZ", 0)
    blocks = RowBlocks(m, 2)
    assert len(blocks.blocks) == 2
    for b, (r0, r1) in zip(blocks.blocks, blocks.rows):
        assert np.shares_memory(b.data, m.data)
        assert (b != m[r0:r1]).nnz == 0


def test_small_matrices_are_not_split():
    m = _matrix(100, 100)
    assert m.nnz < threads.MIN_SPLIT_NNZ
    assert len(RowBlocks(m, 4).blocks) == 1


def test_run_split_keeps_order_and_waits_for_every_part():
    ended = []

    def part(k: int) -> int:
        if k == 1:
            time.sleep(0.05)
        ended.append(k)
        return 10 * k

    assert run_split(part, 3) == [0, 10, 20]
    assert sorted(ended) == [0, 1, 2]

    def failing(k: int) -> int:
        if k == 0:
            raise ValueError("part 0")
        time.sleep(0.05)
        ended.append(100 + k)
        return k

    ended.clear()
    with pytest.raises(ValueError, match="part 0"):
        run_split(failing, 3)
    # the other parts had ended when the error came back
    assert sorted(ended) == [101, 102]


def test_beside_runs_on_another_thread_only_with_two_threads(torch_threads):
    def where() -> str:
        return threading.current_thread().name

    torch_threads(1)
    assert beside(where).result() == threading.current_thread().name
    torch_threads(2)
    assert beside(where).result().startswith("trmd-beside")

    def fails() -> None:
        raise RuntimeError("inside")

    for n in (1, 2):
        torch_threads(n)
        with pytest.raises(RuntimeError, match="inside"):
            beside(fails).result()


def test_beside_lanes_do_not_wait_for_each_other(torch_threads):
    """A job in one lane runs while another lane's job waits for it (in one lane this would
    wait forever: the second job queued behind the first)."""
    torch_threads(2)
    started = threading.Event()
    first = beside(lambda: started.wait(10.0), lane="test-a")
    second = beside(started.set, lane="test-b")
    assert first.result() is True
    second.result()


def test_blur_matrix_in_bands_is_the_one_band_matrix(torch_threads):
    w, h = 90, 70
    motion = GlobalMotion((9.0, -5.0), (6.0, 4.0), 0.03, -0.01, ((w - 1) / 2, (h - 1) / 2))
    ops = []
    for n in (1, 2, 3):
        torch_threads(n)
        ops.append(BlurOperator(motion, w, h))
    one = ops[0]
    assert one.matrix.has_canonical_format and one.matrix_t.has_canonical_format
    assert (one.matrix_t != one.matrix.T.tocsr()).nnz == 0
    for op in ops[1:]:
        for a, b in ((op.matrix, one.matrix), (op.matrix_t, one.matrix_t)):
            assert a.has_canonical_format
            assert np.array_equal(a.indptr, b.indptr) and np.array_equal(a.indices, b.indices)
            assert np.array_equal(a.data, b.data)


def test_deconvolution_does_not_depend_on_the_thread_count(torch_threads, monkeypatch):
    w, h = 120, 90
    rng = np.random.default_rng(3)
    blurry = rng.random((h, w)).astype(np.float32)
    motion = GlobalMotion((12.0, 3.0), (0.0, 0.0), 0.0, 0.0, ((w - 1) / 2, (h - 1) / 2))
    monkeypatch.setattr(threads, "MIN_SPLIT_NNZ", 0)
    out = []
    for n in (1, 2):
        torch_threads(n)
        out.append(deconvolve(blurry, motion).middle.numpy())
    assert np.array_equal(out[0], out[1])


def test_map_shared_keeps_the_items_order(torch_threads):
    seen: list[str] = []

    def square(x: int) -> int:
        seen.append(threading.current_thread().name)
        return x * x

    for n in (1, 2, 3):
        torch_threads(n)
        seen.clear()
        assert threads.map_shared(square, range(7)) == [x * x for x in range(7)]
        assert len({s.startswith("trmd-sparse") for s in seen}) == (1 if n == 1 else 2)
    assert threads.map_shared(square, []) == []


def _run_without_omp(code: str, *args: str, **extra: str) -> None:
    """``python -c code args`` in a process whose OMP_NUM_THREADS is ``extra``'s or unset."""
    import os

    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    subprocess.run([sys.executable, "-c", code, *args], check=True, env={**env, **extra})


def test_thread_count_does_not_load_torch():
    # a process reading events only is not made to import torch (a second) for the count:
    # it counts its cores, or takes OMP_NUM_THREADS (a --jobs worker's) as torch would
    import os

    code = ("import sys, os; from trmd_cli import threads; n = threads.product_threads(); "
            "assert 'torch' not in sys.modules; "
            "assert n == max(1, min(int(sys.argv[1]), 4)), n; "
            "import torch; torch.set_num_threads(1); assert threads.product_threads() == 1")
    _run_without_omp(code, str(len(os.sched_getaffinity(0))))
    _run_without_omp(code, "3", OMP_NUM_THREADS="3")


def test_threads_for_edi_do_not_load_torch():
    # `--threads` on a method without weights: its count is taken without importing torch,
    # and torch, imported later, starts with it
    code = ("import sys; from trmd_cli.methods import MethodConfig, make_method; "
            "from trmd_cli import threads; make_method(MethodConfig(method='edi', threads=1)); "
            "assert 'torch' not in sys.modules; assert threads.product_threads() == 1; "
            "import torch; assert torch.get_num_threads() == 1")
    _run_without_omp(code)
