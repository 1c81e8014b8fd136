"""The training loop in-process: it learns, resumes exactly, keeps its time budget, writes its
outputs, and trains without ground truth when the recipe says so."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from tests.helpers.training import make_gopro_h5, read_log, recipe, write_trmd_h5
from trmd_cli.errors import InputError, OutputExistsError, WeightsError
from trmd_cli.metrics import psnr
from trmd_cli.models.weights import load_weights
from trmd_cli.train.data import build_data
from trmd_cli.train.loop import LOG_COLUMNS, evaluate, lr_at, train
from trmd_cli.train.recipe import apply_overrides


def model_tensors(run: Path) -> dict[str, torch.Tensor]:
    return {k: v for k, v in load_file(str(run / "checkpoint.safetensors")).items()
            if k.startswith("model/")}


def test_lr_schedule_hand_values():
    r = recipe("optim.lr=1.0", "optim.min_lr=0.0", "optim.warmup_steps=4")
    assert [lr_at(s, r, 104) for s in range(4)] == [0.25, 0.5, 0.75, 1.0]
    assert lr_at(4, r, 104) == pytest.approx(1.0)
    assert lr_at(54, r, 104) == pytest.approx(0.5)  # half-way through the cosine
    assert lr_at(104, r, 104) == pytest.approx(0.0, abs=1e-12)
    c = recipe("optim.schedule='constant'", "optim.warmup_steps=0", "optim.lr=0.1")
    assert lr_at(77, c, 100) == 0.1


def test_training_beats_the_blurry_frame_and_writes_its_outputs(gopro, tmp_path):
    r = recipe("train.steps=40", "train.val_every=20", "train.checkpoint_every=20")
    plan = build_data([gopro], r)
    # the untrained network predicts R ≈ 0, i.e. every frame = the blurry one
    base_mid = np.mean([psnr(plan.val[i]["blurry"], plan.val[i]["sharp"][3])
                        for i in range(len(plan.val))])
    res = train([gopro], recipe=r, run_dir=tmp_path / "run")
    assert res.stopped == "done" and res.steps == 40 and res.epochs == pytest.approx(20.0)
    assert res.val_psnr_mid > base_mid + 3.0
    assert res.best_val_psnr_mid >= res.val_psnr_mid - 1e-9
    run = tmp_path / "run"
    assert {p.name for p in run.iterdir()} == {
        "checkpoint.safetensors", "log.csv", "curve.png", "best.safetensors",
        "final.safetensors", "recipe.json"}
    rows = read_log(run / "log.csv")
    assert tuple(rows[0]) == LOG_COLUMNS
    assert [int(r["step"]) for r in rows] == list(range(5, 45, 5))
    assert [r["step"] for r in rows if r["val_psnr_mid"]] == ["20", "40"]
    assert float(rows[-1]["val_psnr_mid"]) == pytest.approx(res.val_psnr_mid, abs=1e-5)
    # the evaluation figure recomputed from the saved weights (fp16) agrees
    model, meta = load_weights(run / "final.safetensors")
    mid, seq, count = evaluate(model, plan.val)
    assert count == len(plan.val)
    assert mid == pytest.approx(res.val_psnr_mid, abs=0.05)
    assert meta["figures"]["steps"] == 40
    assert meta["recipe"]["model"]["name"] == "test_trmd"


def test_resume_gives_the_uninterrupted_result(gopro, tmp_path):
    r = recipe("train.steps=12", "train.val_every=6", "train.checkpoint_every=4")
    a = train([gopro], recipe=r, run_dir=tmp_path / "a")
    b1 = train([gopro], recipe=r, run_dir=tmp_path / "b", stop_after_steps=5)
    assert b1.stopped == "step_limit" and b1.steps == 5 and b1.final_weights is None
    b2 = train(None, run_dir=tmp_path / "b", resume=True)  # recipe and data from the run
    assert b2.stopped == "done" and b2.steps == 12
    ta, tb = model_tensors(tmp_path / "a"), model_tensors(tmp_path / "b")
    assert ta.keys() == tb.keys()
    for k in ta:
        torch.testing.assert_close(ta[k], tb[k], rtol=1e-6, atol=1e-7, msg=k)
    la, lb = read_log(tmp_path / "a" / "log.csv"), read_log(tmp_path / "b" / "log.csv")
    strip = [{k: v for k, v in row.items() if k != "seconds"} for row in la]
    assert strip == [{k: v for k, v in row.items() if k != "seconds"} for row in lb]
    assert b2.val_psnr_mid == pytest.approx(a.val_psnr_mid, abs=1e-4)


def test_resume_refuses_changed_recipe_or_data_and_an_existing_run(gopro, tmp_path):
    r = recipe("train.steps=2", "train.val_every=2")
    train([gopro], recipe=r, run_dir=tmp_path / "run")
    with pytest.raises(OutputExistsError, match="`resume=True`"):
        train([gopro], recipe=r, run_dir=tmp_path / "run")
    with pytest.raises(InputError, match="optim.lr"):
        train(None, recipe=apply_overrides(r, ["optim.lr=0.5"]), run_dir=tmp_path / "run",
              resume=True)
    other = make_gopro_h5(tmp_path / "other.h5", k=4)
    with pytest.raises(InputError, match="`data` differs"):
        train([other], run_dir=tmp_path / "run", resume=True)
    # speed and length settings may change
    res = train(None, run_dir=tmp_path / "run", resume=True,
                overrides=["train.steps=4", "train.log_every=1"])
    assert res.steps == 4 and any("length changed" in n for n in res.notes)
    with pytest.raises(InputError, match="`init_weights`"):
        train(None, run_dir=tmp_path / "run", resume=True, init_weights=tmp_path / "x")


class FakeClock:
    """Time that passes only when a training step reports: 10 s per step."""

    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


class Ticker:
    def __init__(self, clock: FakeClock) -> None:
        self.clock = clock

    def phase(self, message): ...
    def start(self, **_): ...
    def validated(self, **_): ...
    def note(self, message): ...
    def close(self): ...

    def step(self, **_):
        self.clock.t += 10.0


def test_time_budget_stops_cleanly_with_validation_and_weights(gopro, tmp_path):
    clock = FakeClock()
    r = recipe("train.steps=100", "train.val_every=50", "train.checkpoint_every=50",
               "train.time_budget_minutes=1")
    res = train([gopro], recipe=r, run_dir=tmp_path / "run", clock=clock,
                reporter=Ticker(clock))
    # after k steps 10·k s have passed; it stops when 10·k + 1 s of margin reaches 60 s
    assert res.stopped == "time_budget" and res.steps == 6
    assert res.final_weights is not None and res.final_weights.exists()
    assert res.val_psnr_mid is not None  # validated before stopping
    rows = read_log(tmp_path / "run" / "log.csv")
    assert rows[-1]["step"] == "6" and rows[-1]["val_psnr_mid"]
    # resuming a run whose budget is used up does no further step
    again = train(None, run_dir=tmp_path / "run", resume=True, clock=clock,
                  reporter=Ticker(clock))
    assert again.steps == 6 and again.stopped == "time_budget"


def test_training_without_ground_truth(tmp_path):
    data = write_trmd_h5(tmp_path / "u.h5", sharp=False, k=8, size=32)
    r = recipe("loss.residual=0", "loss.middle=0", "loss.event_consistency=1.0",
               "loss.blur_consistency=1.0", "train.steps=4", "data.batch_size=2",
               "loss.penalty='charbonnier'")
    res = train([data], recipe=r, run_dir=tmp_path / "run")
    assert res.stopped == "done" and res.steps == 4
    assert res.val_psnr_mid is None and any("no ground truth" in n for n in res.notes)
    losses = [float(row["loss"]) for row in read_log(tmp_path / "run" / "log.csv")]
    assert losses and all(np.isfinite(losses))


def test_init_weights_start_from_the_given_weights(gopro, tmp_path):
    r = recipe("train.steps=3", "train.val_every=3")
    first = train([gopro], recipe=r, run_dir=tmp_path / "a")
    src, _ = load_weights(first.final_weights)
    tiny = apply_overrides(r, ["optim.lr=1e-12", "optim.min_lr=0.0", "train.steps=1"])
    train([gopro], recipe=tiny, run_dir=tmp_path / "b", init_weights=first.final_weights)
    got = model_tensors(tmp_path / "b")
    for k, v in src.state_dict().items():
        if v.is_floating_point() and "running" not in k:  # BatchNorm statistics move
            torch.testing.assert_close(got[f"model/{k}"], v.float(), atol=1e-6, rtol=0)
    wrong = apply_overrides(r, ["model.args.feat_width=6"])
    with pytest.raises(WeightsError, match="do not fit"):
        train([gopro], recipe=wrong, run_dir=tmp_path / "c", init_weights=first.final_weights)


def test_too_little_data_for_a_batch(gopro, tmp_path):
    with pytest.raises(InputError, match="no full batch"):
        train([gopro], recipe=recipe("data.batch_size=64"), run_dir=tmp_path / "run")


def test_the_reporter_hears_what_the_run_does_before_its_first_step(gopro, tmp_path):
    """Building the data and the network can take minutes: the reporter is told at once."""
    heard: list[str] = []

    class Recorder(Ticker):
        def phase(self, message):
            heard.append(message)

        def start(self, **_):
            heard.append("start")

    train([gopro], recipe=recipe("train.steps=2"), run_dir=tmp_path / "r",
          reporter=Recorder(FakeClock()))
    assert heard[:3] == ["preparing the training and validation data", "building test_trmd",
                         "start"]
