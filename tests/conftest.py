from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


@pytest.fixture(scope="module")
def gopro(tmp_path_factory) -> Path:
    """A 12-sample GOPRO-layout training set (``tests.helpers.training.make_gopro_h5``)."""
    from tests.helpers.training import make_gopro_h5

    return make_gopro_h5(tmp_path_factory.mktemp("data") / "g.h5", k=12)


@pytest.fixture
def no_shipped_weights(monkeypatch) -> None:
    """Run as an installation without shipped weights would: the default weights file is
    looked for under a name that does not exist."""
    from trmd_cli.models import weights

    monkeypatch.setattr(weights, "DEFAULT_WEIGHTS", "absent.safetensors")
    assert not weights.default_weights_path().is_file()


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
