"""Checkpoints (safetensors + JSON metadata, atomic, no pickle) and the training-curve PNG."""

from __future__ import annotations

import json
import random
import struct

import numpy as np
import pytest
import torch

from trmd_cli.errors import FormatError
from trmd_cli.models import RENetInputs, create_model
from trmd_cli.train.checkpoint import (
    is_checkpoint,
    load_checkpoint,
    read_checkpoint_state,
    save_checkpoint,
)
from trmd_cli.train.plots import COLORS, draw_curve, log_ticks, nice_ticks, write_curve


def trained_pair(steps: int = 2):
    torch.manual_seed(0)
    model = create_model("test_trmd")
    opt = torch.optim.Adam(model.parameters(), lr=1e-2, foreach=False)
    g = torch.Generator().manual_seed(1)
    data = [(torch.rand(2, 1, 16, 16, generator=g), torch.randn(2, 6, 16, 16, generator=g))
            for _ in range(steps + 1)]
    for b, v in data[:steps]:
        opt.zero_grad()
        model(RENetInputs(b, v)).square().mean().backward()
        opt.step()
    return model, opt, data[steps]


def one_step(model, opt, batch):
    opt.zero_grad()
    model(RENetInputs(*batch)).square().mean().backward()
    opt.step()


def test_round_trip_restores_model_optimiser_rng_and_state(tmp_path):
    model, opt, nxt = trained_pair()
    random.seed(11)
    np.random.seed(12)
    torch.manual_seed(13)
    path = save_checkpoint(tmp_path / "ck.safetensors", model=model, optimizer=opt,
                           state={"step": 2, "history": [{"step": 2, "loss": 0.5}]})
    expected_draws = (random.random(), float(np.random.rand()), float(torch.rand(())))

    torch.manual_seed(99)  # a different init and RNG state
    model2 = create_model("test_trmd")
    opt2 = torch.optim.Adam(model2.parameters(), lr=1e-2, foreach=False)
    doc = load_checkpoint(path, model=model2, optimizer=opt2)
    assert doc["step"] == 2 and doc["history"] == [{"step": 2, "loss": 0.5}]
    assert (random.random(), float(np.random.rand()), float(torch.rand(()))) == expected_draws
    for (k, a), b in zip(model.state_dict().items(), model2.state_dict().values(), strict=True):
        assert torch.equal(a, b), k
    # the next step is identical: the optimiser moments and step counts came back
    one_step(model, opt, nxt)
    one_step(model2, opt2, nxt)
    for a, b in zip(model.parameters(), model2.parameters(), strict=True):
        assert torch.equal(a, b)


def test_checkpoint_is_safetensors_with_json_metadata(tmp_path):
    model, opt, _ = trained_pair(1)
    path = save_checkpoint(tmp_path / "ck.safetensors", model=model, optimizer=opt,
                           state={"step": 1})
    raw = path.read_bytes()
    (header_len,) = struct.unpack("<Q", raw[:8])
    header = json.loads(raw[8:8 + header_len])
    assert "model/head.weight" in header and "rng/torch" in header
    assert any(k.startswith("optim/") for k in header)
    meta = json.loads(header["__metadata__"]["trmd_checkpoint"])
    assert meta["step"] == 1 and meta["format"] == 1
    assert read_checkpoint_state(path)["step"] == 1


def test_a_failed_save_leaves_the_previous_checkpoint(tmp_path, monkeypatch):
    model, opt, _ = trained_pair(1)
    path = save_checkpoint(tmp_path / "ck.safetensors", model=model, optimizer=opt,
                           state={"step": 1})
    before = path.read_bytes()

    from trmd_cli import write

    real_write = write._OutputFile.write

    def boom(self, data):  # interrupted half way through writing the bytes
        real_write(self, bytes(data)[: len(data) // 2])
        raise KeyboardInterrupt

    monkeypatch.setattr(write._OutputFile, "write", boom)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(path, model=model, optimizer=opt, state={"step": 2})
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ck.safetensors"]


#: a child that saves a checkpoint of a 16 MiB model over and over, until it is killed
_SAVING_FOREVER = """
import sys, torch
from trmd_cli.train.checkpoint import save_checkpoint
model = torch.nn.Linear(2048, 2048)
opt = torch.optim.SGD(model.parameters(), lr=0.1)
while True:
    save_checkpoint(sys.argv[1], model=model, optimizer=opt, state={"step": 1})
"""


@pytest.mark.skipif(not hasattr(__import__("signal"), "SIGKILL"), reason="kill -9")
def test_kill_9_while_saving_leaves_only_temporaries_the_next_run_removes(tmp_path):
    """safetensors' save_file wrote a temporary of its own (.tmpXXXXXX) that no trmd sweep
    knew: killed inside it, the run folder kept it for good."""
    import os
    import re
    import signal
    import subprocess
    import sys
    import time

    from trmd_cli.train.loop import _prepare_run_dir
    from trmd_cli.train.steps import CHECKPOINT

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST")}
    proc = subprocess.Popen([sys.executable, "-c", _SAVING_FOREVER, str(run_dir / CHECKPOINT)],
                            env=env)
    foreign = re.compile(r"\.tmp[A-Za-z0-9]{6}")
    try:
        end = time.monotonic() + 60
        while time.monotonic() < end and proc.poll() is None:
            names = [p for p in run_dir.iterdir() if p.name != CHECKPOINT]
            if any(foreign.fullmatch(p.name) for p in names) or any(
                    p.stat().st_size > 0 for p in names if ".trmd-" in p.name):
                break  # in the middle of a save
            time.sleep(0.001)
        else:
            pytest.fail("the child never got to save")
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    left = [p.name for p in run_dir.iterdir() if p.name != CHECKPOINT]
    assert left and not any(foreign.fullmatch(n) for n in left), left
    (run_dir / ".tmpAbC123").write_bytes(b"left by an older trmd")  # safetensors' own, stale
    _prepare_run_dir(run_dir, fresh=False)  # what resuming the run does first
    assert [p.name for p in run_dir.iterdir()] in ([], [CHECKPOINT])


def test_unreadable_or_foreign_files_are_refused(tmp_path):
    from safetensors.torch import save_file

    with pytest.raises(FormatError, match="no checkpoint"):
        read_checkpoint_state(tmp_path / "none.safetensors")
    (tmp_path / "junk.safetensors").write_bytes(b"\x80\x04junk")
    with pytest.raises(FormatError, match="not a readable checkpoint"):
        read_checkpoint_state(tmp_path / "junk.safetensors")
    save_file({"w": torch.zeros(2)}, str(tmp_path / "weights.safetensors"))
    with pytest.raises(FormatError, match="not a trmd training checkpoint"):
        read_checkpoint_state(tmp_path / "weights.safetensors")


def test_checkpoint_of_another_architecture_is_refused(tmp_path):
    model, opt, _ = trained_pair(1)
    path = save_checkpoint(tmp_path / "ck.safetensors", model=model, optimizer=opt,
                           state={"step": 1})
    other = create_model("test_trmd", feat_width=6)
    with pytest.raises(FormatError, match="does not fit"):
        load_checkpoint(path, model=other,
                        optimizer=torch.optim.Adam(other.parameters(), foreach=False))


def test_init_from_another_runs_checkpoint_takes_its_weights_only(tmp_path):
    from trmd_cli.models.weights import save_weights
    from trmd_cli.train.loop import _load_init
    from trmd_cli.train.recipe import apply_overrides, load_recipe

    model, opt, _ = trained_pair(2)
    ck = save_checkpoint(tmp_path / "ck.safetensors", model=model, optimizer=opt,
                         state={"step": 2, "recipe": {"model": {"name": "test_trmd"}}})
    weights = save_weights(tmp_path / "w.safetensors", model, meta={}, half=False)
    assert is_checkpoint(ck) and not is_checkpoint(weights)
    assert not is_checkpoint(tmp_path / "missing.safetensors")
    recipe = apply_overrides(load_recipe(None), ['model.name="test_trmd"'])
    torch.manual_seed(5)
    fresh = create_model("test_trmd")
    _load_init(fresh, ck, recipe)
    for (k, a), b in zip(model.state_dict().items(), fresh.state_dict().values(), strict=True):
        assert torch.equal(a, b), k
    other = create_model("test_trmd", feat_width=6)
    with pytest.raises(FormatError, match="trained test_trmd"):
        _load_init(other, ck, recipe)


# --------------------------------------------------------------------------------------------
# Curve


def test_nice_ticks():
    assert nice_ticks(0, 10, 5) == [0, 2, 4, 6, 8, 10]
    assert nice_ticks(0.3, 0.9, 5) == pytest.approx([0.4, 0.6, 0.8])
    assert nice_ticks(5, 5) == [5]
    assert log_ticks(0.003, 0.06) == pytest.approx([0.005, 0.01, 0.02, 0.05])
    assert log_ticks(1e-4, 10) == pytest.approx([1e-4, 1e-3, 1e-2, 0.1, 1, 10])


def test_tick_labels_stay_distinct_on_long_step_axes():
    from trmd_cli.train.plots import _fmt

    labels = [_fmt(t) for t in nice_ticks(0, 26000, 6)]
    assert labels == ["0", "5000", "10k", "15k", "20k", "25k"]
    assert _fmt(2_500_000) == "2.5M" and _fmt(3e-3) == "3e-3" and _fmt(0.5) == "0.5"


def _mask(img: np.ndarray, colour) -> np.ndarray:
    return np.all(np.abs(img.astype(int) - np.array(colour)) <= 30, axis=2)


def test_curve_draws_falling_loss_and_rising_psnr():
    history = [{"step": s, "loss": 1.0 / s, "val_psnr_mid": None, "val_psnr_seq": None}
               for s in range(10, 1010, 10)]
    for s, row in zip(range(10, 1010, 10), history, strict=True):
        if s % 200 == 0:
            row.update(val_psnr_mid=20 + s / 100, val_psnr_seq=19 + s / 100)
    img = draw_curve(history, width=900, height=640)
    assert img.shape == (640, 900, 3) and img.dtype == np.uint8
    top, bottom = img[:320], img[320:]
    loss = _mask(top, COLORS["loss"])
    ys, xs = np.nonzero(loss[:, 80:700])  # leave the legend out
    # the line starts high on the left and ends low on the right
    left, right = ys[xs < 40], ys[xs > 580]
    assert left.size and right.size and left.mean() < right.mean() - 100
    mid = _mask(bottom, COLORS["val_psnr_mid"])
    ys, xs = np.nonzero(mid[:, 80:700])
    left, right = ys[xs < 250], ys[xs > 500]
    assert left.size and right.size and left.mean() > right.mean() + 50  # rising = going up
    assert _mask(bottom, COLORS["val_psnr_seq"]).any()


def test_curve_of_an_empty_log_and_the_png(tmp_path):
    import cv2

    assert draw_curve([]).shape == (640, 900, 3)
    path = write_curve(tmp_path / "c.png", [{"step": 1, "loss": 0.2}, {"step": 2, "loss": 0.1}])
    img = cv2.imread(str(path))
    assert img is not None and img.shape == (640, 900, 3)
