"""The weight average (``optim.ema``): its recursion by hand, that validation and the written
weights use it, that it survives a resume exactly, and that fine-tuning from a run starts
from it."""

from __future__ import annotations

import pytest
import torch
from safetensors.torch import load_file

from tests.helpers.training import make_gopro_h5, recipe
from trmd_cli.errors import InputError
from trmd_cli.models.weights import load_weights
from trmd_cli.train.ema import WeightAverage
from trmd_cli.train.loop import train
from trmd_cli.train.recipe import apply_overrides


@pytest.fixture(scope="module")
def gopro(tmp_path_factory):
    return make_gopro_h5(tmp_path_factory.mktemp("data") / "g.h5", k=12)


def test_average_follows_the_recursion_by_hand():
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Conv2d(1, 2, 3), torch.nn.BatchNorm2d(2))
    avg = WeightAverage(net, decay=0.5)
    w = net[0].weight.detach().clone()
    expect_w = w.clone()
    expect_mean = net[1].running_mean.clone()
    for k in range(4):
        with torch.no_grad():
            net[0].weight.add_(float(k + 1))
        net(torch.randn(3, 1, 5, 5))  # train-mode forward: BatchNorm statistics move
        d = min(0.5, (1 + k) / (10 + k))  # 0.1, 0.18…, 0.25, 0.3077: the ramp, below 0.5
        expect_w = d * expect_w + (1 - d) * net[0].weight.detach()
        expect_mean = d * expect_mean + (1 - d) * net[1].running_mean
        avg.update(net)
    torch.testing.assert_close(avg.module[0].weight, expect_w)
    torch.testing.assert_close(avg.module[1].running_mean, expect_mean)
    # integer buffers are copied, not averaged
    assert int(avg.module[1].num_batches_tracked) == int(net[1].num_batches_tracked) == 4
    assert avg.updates == 4 and avg.rate() == 0.5 * 0 + min(0.5, 5 / 14)
    assert not any(p.requires_grad for p in avg.module.parameters())


def test_decay_settles_at_the_given_value():
    avg = WeightAverage(torch.nn.Linear(1, 1), decay=0.999, updates=100_000)
    assert avg.rate() == 0.999
    with pytest.raises(ValueError):
        WeightAverage(torch.nn.Linear(1, 1), decay=1.0)


def test_recipe_refuses_a_decay_of_one(gopro, tmp_path):
    with pytest.raises(InputError, match="optim.ema"):
        train([gopro], recipe=recipe("optim.ema=1.0"), run_dir=tmp_path / "run")


def test_written_weights_are_the_average_and_resume_is_exact(gopro, tmp_path):
    r = recipe("train.steps=10", "train.val_every=5", "train.checkpoint_every=4",
               "optim.ema=0.9")
    a = train([gopro], recipe=r, run_dir=tmp_path / "a")
    ck = load_file(str(tmp_path / "a" / "checkpoint.safetensors"))
    ema = {k[4:]: v for k, v in ck.items() if k.startswith("ema/")}
    raw = {k[6:]: v for k, v in ck.items() if k.startswith("model/")}
    assert ema.keys() == raw.keys()
    final, _ = load_weights(a.final_weights)
    moved = 0
    for k, v in final.state_dict().items():
        if v.is_floating_point():
            # parameters are stored as float16, BatchNorm statistics as float32
            assert torch.equal(v.float(), ema[k].half().float()) or torch.equal(v, ema[k]), k
            moved += int(not torch.allclose(ema[k], raw[k]))
    assert moved > 0  # the average is not the last iterate

    b1 = train([gopro], recipe=r, run_dir=tmp_path / "b", stop_after_steps=6)
    assert b1.stopped == "step_limit"
    b2 = train(None, run_dir=tmp_path / "b", resume=True)
    assert b2.steps == 10
    ck_b = load_file(str(tmp_path / "b" / "checkpoint.safetensors"))
    for k, v in ck.items():
        if k.startswith(("ema/", "model/")):
            torch.testing.assert_close(ck_b[k], v, rtol=1e-6, atol=1e-7, msg=k)
    assert b2.val_psnr_mid == pytest.approx(a.val_psnr_mid, abs=1e-4)


def test_fine_tuning_from_a_run_starts_from_its_average(gopro, tmp_path):
    r = recipe("train.steps=4", "train.val_every=4", "optim.ema=0.9")
    train([gopro], recipe=r, run_dir=tmp_path / "a")
    ck = load_file(str(tmp_path / "a" / "checkpoint.safetensors"))
    tiny = apply_overrides(recipe(), ["optim.lr=1e-12", "optim.min_lr=0.0", "train.steps=1",
                                      "train.val_every=1"])
    train([gopro], recipe=tiny, run_dir=tmp_path / "b",
          init_weights=tmp_path / "a" / "checkpoint.safetensors")
    got = load_file(str(tmp_path / "b" / "checkpoint.safetensors"))
    for k, v in ck.items():
        if k.startswith("ema/") and v.is_floating_point() and "running" not in k:
            torch.testing.assert_close(got["model/" + k[4:]], v, atol=1e-6, rtol=0, msg=k)
