"""`trmd train` from the command line: the happy path, one-line errors, surviving `kill -9`,
and a 2-process DDP run under torchrun (gloo on CPU)."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file
from typer.testing import CliRunner

from tests.helpers.data import ROOT, SHARED
from tests.helpers.training import make_gopro_h5
from trmd_cli.cli.app import app
from trmd_cli.train.checkpoint import read_checkpoint_state
from trmd_cli.train.loop import train
from trmd_cli.train.recipe import load_recipe

runner = CliRunner()

RECIPE = """
name = "tiny"
[model]
name = "test_trmd"
[data]
crop = 32
batch_size = 2
val_fraction = 0.25
[optim]
lr = 3e-3
warmup_steps = 3
[train]
steps = 6
val_every = 3
log_every = 2
checkpoint_every = 3
checkpoint_minutes = 0
threads = 1
"""


@pytest.fixture(scope="module")
def setup(tmp_path_factory) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("cli")
    (d / "r.toml").write_text(RECIPE)
    return make_gopro_h5(d / "g.h5", k=8), d / "r.toml"


def env() -> dict[str, str]:
    # one thread per process and the source tree importable from a subprocess
    src = str(ROOT / "src")
    return {**os.environ, "OMP_NUM_THREADS": "1",
            "PYTHONPATH": os.pathsep.join([src, os.environ.get("PYTHONPATH", "")])}


def model_tensors(run: Path) -> dict[str, torch.Tensor]:
    return {k: v for k, v in load_file(str(run / "checkpoint.safetensors")).items()
            if k.startswith("model/")}


def test_train_command_runs_and_summarises(setup, tmp_path):
    data, rec = setup
    out = tmp_path / "run"
    r = runner.invoke(app, ["train", "--data", str(data), "--recipe", str(rec), "--out", str(out),
                            "--set", "train.steps=4"])
    assert r.exit_code == 0, r.output
    assert "trained 4/4 steps" in r.stdout and "validation PSNR: middle" in r.stdout
    assert (out / "final.safetensors").exists() and (out / "curve.png").exists()
    saved = json.loads((out / "recipe.json").read_text())
    assert saved["recipe"]["train"]["steps"] == 4 and saved["data"] == [str(data.resolve())]
    # `info` shows the run's own validation figures
    d = json.loads(runner.invoke(app, ["info", str(out / "final.safetensors"), "--json"]).stdout)
    shown = re.search(r"validation PSNR: middle ([\d.]+)", r.stdout)
    assert d["validation"]["trmd"]["psnr_mid"] == pytest.approx(float(shown[1]), abs=0.01)
    # continuing the finished run with a longer length
    r = runner.invoke(app, ["train", "--out", str(out), "--resume", "--set", "train.steps=6"])
    assert r.exit_code == 0, r.output
    assert "trained 6/6 steps" in r.stdout


def test_stop_after_leaves_a_run_to_resume(setup, tmp_path):
    data, rec = setup
    out = tmp_path / "run"
    r = runner.invoke(app, ["train", "--data", str(data), "--recipe", str(rec), "--out", str(out),
                            "--set", "train.steps=5", "--stop-after", "2"])
    assert r.exit_code == 0, r.output
    assert "trained 2/5 steps" in r.stdout and "--stop-after" in r.stdout
    assert (out / "checkpoint.safetensors").exists() and not (out / "final.safetensors").exists()
    r = runner.invoke(app, ["train", "--out", str(out), "--resume"])
    assert r.exit_code == 0, r.output
    assert "trained 5/5 steps" in r.stdout and (out / "final.safetensors").exists()


@pytest.mark.parametrize("args, needle", [
    (["--recipe", "{bad}"], "did you mean 'lr'"),
    (["--set", "optim.lr=-1"], "optim.lr"),
    (["--set", "model.name='nope'"], "unknown model 'nope'"),
    (["--data", "{missing}"], "training data not found"),
    (["--out", "{nonempty}"], "--resume to continue"),
    (["--out", "{fresh}", "--resume"], "no checkpoint to resume from"),
    (["--init-weights", "{missing}"], "weights file not found"),
])
def test_bad_input_gives_one_line_and_exit_2(setup, tmp_path, args, needle):
    data, rec = setup
    (tmp_path / "bad.toml").write_text("[optim]\nlrr = 1\n")
    (tmp_path / "nonempty").mkdir()
    (tmp_path / "nonempty" / "keep.txt").write_text("keep me")
    subs = {"{bad}": str(tmp_path / "bad.toml"), "{missing}": str(tmp_path / "missing.h5"),
            "{nonempty}": str(tmp_path / "nonempty"), "{fresh}": str(tmp_path / "fresh")}
    args = [subs.get(a, a) for a in args]
    base = ["train", "--data", str(data), "--recipe", str(rec)]
    if "--out" not in args:
        base += ["--out", str(tmp_path / "out")]
    r = runner.invoke(app, base + args)
    assert r.exit_code == 2, r.output
    assert needle in r.output
    assert "Traceback" not in r.output
    assert (tmp_path / "nonempty" / "keep.txt").read_text() == "keep me"
    assert not (tmp_path / "out" / "final.safetensors").exists()


@pytest.mark.parametrize("workers", [0, 1])
def test_a_run_that_fails_before_its_first_checkpoint_leaves_nothing(setup, tmp_path, workers):
    """Else a rerun would be refused ('not empty') and a resume too ('no checkpoint'). The
    line names the file and the fix, also when a DataLoader worker met it."""
    _, rec = setup
    bad = tmp_path / "imgs"
    bad.mkdir()
    (bad / "bad.png").write_bytes(b"not an image")
    r = runner.invoke(app, ["train", "--data", str(bad), "--recipe", str(rec), "--out",
                            str(tmp_path / "run"), "--set", "data.length=4",
                            "--set", f"data.num_workers={workers}"])
    assert r.exit_code == 2 and "bad.png: not a readable image" in r.output, r.output
    assert "Caught" not in r.output
    assert not (tmp_path / "run").exists()
    (tmp_path / "mine").mkdir()
    r = runner.invoke(app, ["train", "--data", str(bad), "--recipe", str(rec), "--out",
                            str(tmp_path / "mine"), "--set", "data.length=4",
                            "--set", "data.num_workers=0"])
    assert r.exit_code == 2 and (tmp_path / "mine").is_dir()  # the user's own folder stays
    assert not any((tmp_path / "mine").iterdir())


def test_info_describes_a_training_checkpoint(setup, tmp_path):
    data, rec = setup
    out = tmp_path / "run"
    r = runner.invoke(app, ["train", "--data", str(data), "--recipe", str(rec), "--out",
                            str(out), "--stop-after", "3"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["info", str(out / "checkpoint.safetensors"), "--json"])
    assert r.exit_code == 0, r.output
    assert '"checkpoint"' in r.stdout


def test_missing_data_or_out_are_usage_errors(setup, tmp_path):
    _, rec = setup
    r = runner.invoke(app, ["train", "--recipe", str(rec), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "--data" in r.output
    r = runner.invoke(app, ["train", "--resume"])
    assert r.exit_code == 2 and "--out" in r.output


def test_training_survives_kill_9(setup, tmp_path):
    data, rec = setup
    steps = ["--set", "train.steps=150", "--set", "train.checkpoint_every=5",
             "--set", "train.val_every=150", "--set", "train.log_every=5"]
    run = tmp_path / "killed"
    cmd = [sys.executable, "-m", "trmd_cli", "train", "--data", str(data), "--recipe", str(rec),
           "--out", str(run), *steps]
    proc = subprocess.Popen(cmd, env=env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            if (run / "checkpoint.safetensors").exists():
                break
            time.sleep(0.02)
        assert proc.poll() is None, "the run ended before it could be killed: " + \
            proc.stderr.read().decode()[-500:]
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    killed_at = read_checkpoint_state(run / "checkpoint.safetensors")["step"]
    assert 5 <= killed_at < 150 and not (run / "final.safetensors").exists()

    res = subprocess.run([sys.executable, "-m", "trmd_cli", "train", "--out", str(run),
                          "--resume"], env=env(), capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "trained 150/150 steps" in res.stdout
    assert not list(run.glob(".*tmp*"))  # no temporaries left behind

    # the same run, uninterrupted, in this process
    recipe = load_recipe(rec, overrides=[s for s in steps if s != "--set"])
    train([data], recipe=recipe, run_dir=tmp_path / "straight")
    a, b = model_tensors(tmp_path / "straight"), model_tensors(run)
    for k in a:
        torch.testing.assert_close(b[k], a[k], rtol=1e-5, atol=1e-6, msg=k)


@pytest.mark.skipif(shutil.which("torchrun") is None, reason="torchrun not on PATH")
def test_two_process_ddp_run_under_torchrun(setup, tmp_path):
    data, rec = setup
    run = tmp_path / "ddp"
    cmd = ["torchrun", "--standalone", "--nproc_per_node=2", "-m", "trmd_cli", "train",
           "--data", str(data), "--recipe", str(rec), "--out", str(run),
           "--set", "train.steps=4", "--set", "data.batch_size=1"]
    res = subprocess.run(cmd, env=env(), capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.count("trained 4/4 steps") == 1  # only rank 0 speaks
    state = read_checkpoint_state(run / "checkpoint.safetensors")
    assert state["world"] == 2 and state["step"] == 4
    # each process draws its share: 6 training samples / 2 processes / batch 1 = 3 per epoch
    assert state["batches_per_epoch"] == 3
    assert [int(r["step"]) for r in state["history"]] == [2, 3, 4]  # log 2, 4; validate 3
    assert state["last_val"]["psnr_mid"] > 20




@pytest.mark.skipif(not (SHARED / "images" / "skimage").exists(), reason="../shared/data absent")
def test_image_folder_is_simulated_on_the_fly(setup, tmp_path):
    _, rec = setup
    out = tmp_path / "imgs"
    r = runner.invoke(app, ["train", "--data", str(SHARED / "images" / "skimage"),
                            "--recipe", str(rec), "--out", str(out), "--set", "train.steps=2",
                            "--set", "data.length=4", "--set", "data.val_samples=2",
                            "--set", "train.val_every=2"])
    assert r.exit_code == 0, r.output
    assert "trained 2/2 steps" in r.stdout and "validation PSNR" in r.stdout
    saved = json.loads((out / "recipe.json").read_text())
    assert saved["validation"].startswith("held out")


def test_a_stopped_run_leaves_weights_every_command_accepts(setup, tmp_path):
    """After --stop-after only checkpoint.safetensors exists: deblur, hfr and info take it as
    weights (the run's weight average when it keeps one), and it computes what the network in
    the checkpoint computes."""
    import numpy as np
    import torch

    from trmd_cli.models.weights import describe_weights, load_weights
    from trmd_cli.train.checkpoint import read_checkpoint_state
    from trmd_cli.train.loop import build_model

    data, rec = setup
    out = tmp_path / "run"
    r = runner.invoke(app, ["train", "--data", str(data), "--recipe", str(rec), "--out", str(out),
                            "--stop-after", "3"])
    assert r.exit_code == 0, r.output
    ckpt = out / "checkpoint.safetensors"
    assert ckpt.is_file() and not (out / "final.safetensors").exists()

    model, meta = load_weights(ckpt)
    assert meta["checkpoint"]["step"] == 3 and meta["n"] == 3
    # the same tensors as the checkpoint's own model (no weight average in this recipe)
    doc = read_checkpoint_state(ckpt)
    ref = build_model(load_recipe(rec))
    from safetensors.torch import load_file

    ref.load_state_dict({k[6:]: v for k, v in load_file(str(ckpt)).items()
                         if k.startswith("model/")})
    for (ka, a), (kb, b) in zip(model.state_dict().items(), ref.state_dict().items()):
        assert ka == kb and torch.equal(a, b), ka
    assert doc["step"] == 3

    d = describe_weights(ckpt)
    assert d["architecture"] == "test_trmd" and d["checkpoint"]["step"] == 3
    assert d["parameters"] == sum(p.numel() for p in ref.parameters())

    img = tmp_path / "b.png"
    ev = tmp_path / "e.npz"
    from trmd_cli.events import Exposure, make_stream
    from trmd_cli.write import write_events_npz, write_image

    rng = np.random.default_rng(0)
    write_image(img, rng.random((24, 32)).astype(np.float32))
    t = np.sort(rng.integers(0, 10_000, 3000))
    write_events_npz(ev, make_stream(rng.integers(0, 32, 3000), rng.integers(0, 24, 3000), t,
                                     rng.integers(0, 2, 3000), 32, 24), [Exposure(0, 10_000)])
    for cmd, target in (("deblur", tmp_path / "o"), ("hfr", tmp_path / "o2")):
        r = runner.invoke(app, [cmd, str(img), str(ev), "-o", str(target), "--weights",
                                str(ckpt), "--contrast", "0.2"])
        assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["info", str(ckpt)])
    assert r.exit_code == 0 and "test_trmd" in r.stdout, r.output
