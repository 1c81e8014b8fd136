from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

#: real recordings and images beside the repo (never copied into it)
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"

needs_shared = pytest.mark.skipif(not SHARED.exists(), reason="../shared/data is absent")


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def random_stream(rng, n=5000, width=40, height=30, t_max=100_000):
    from trmd_cli.events import make_stream

    t = np.sort(rng.integers(0, t_max, n))
    return make_stream(rng.integers(0, width, n), rng.integers(0, height, n), t,
                       rng.integers(0, 2, n), width, height)


def pytest_configure(config):
    import os

    # under pytest-xdist each worker gets one thread: two workers already fill the two cores
    if os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        os.environ.setdefault("MKL_NUM_THREADS", "1")
    # a shell starts background jobs (`cmd &` without job control, nohup) with SIGINT ignored;
    # Python then keeps it ignored, in this process and in every command it starts, and the
    # Ctrl-C tests would test nothing. Restore Python's handler: children then get the default.
    import signal

    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        try:
            signal.signal(signal.SIGINT, signal.default_int_handler)
        except ValueError:  # not the main thread: leave it
            pass
