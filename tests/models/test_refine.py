"""The full-resolution refinement (``refine``): it starts as an identity, so weights trained
without it carry over exactly; it learns from the first step; it is counted, saved and loaded;
and a training run can grow a network from a run that had none."""

from __future__ import annotations

import pytest
import torch
from safetensors.torch import load_file

from tests.helpers.training import make_gopro_h5, recipe
from tests.helpers.training import net_inputs as _inputs
from tests.helpers.training import trained_like as _trained_like
from trmd_cli.errors import InputError
from trmd_cli.models import RENetInputs, count_macs, create_model
from trmd_cli.models.grow import load_grown
from trmd_cli.models.weights import load_weights, save_weights
from trmd_cli.train.loop import train
from trmd_cli.train.recipe import apply_overrides


@pytest.mark.parametrize("prior", ["none", "edi_c"])
def test_grown_network_computes_what_the_weights_computed(prior):
    old = _trained_like(prior=prior)
    new = create_model("test_trmd", prior=prior, refine=3, refine_width=5).eval()
    grown = load_grown(new, old.state_dict())
    assert sorted({k.split(".")[1] for k in grown.names}) == ["0", "1", "2"]
    assert all(k.startswith("refine.") for k in grown.names)
    assert grown.names == list(grown.identity)
    x = RENetInputs(*_inputs(), contrast=0.3)
    with torch.no_grad():
        # the same arithmetic up to float rounding (a dirac conv adds exact zeros)
        torch.testing.assert_close(new(x), old(x), rtol=1e-6, atol=1e-6)


def test_refinement_learns_from_the_first_step():
    net = create_model("test_trmd", refine=2).train()
    load_grown(net, _trained_like().state_dict())
    net(RENetInputs(*_inputs())).square().mean().backward()
    hs = net.up_width
    first = net.refine[0][0].weight.grad
    # the fused features enter through weights that start at zero: they must get a gradient
    assert first[:, hs:].abs().sum() > 0
    assert net.refine[1][0].weight.grad.abs().sum() > 0


def test_load_grown_refuses_other_mismatches():
    old = _trained_like()
    state = old.state_dict()
    net = create_model("test_trmd", refine=1)
    with pytest.raises(RuntimeError, match="missing"):
        load_grown(net, {k: v for k, v in state.items() if not k.startswith("head.")})
    with pytest.raises(RuntimeError, match="unexpected"):
        load_grown(net, {**state, "extra.weight": torch.zeros(1)})
    grown = create_model("test_trmd", refine=2)
    partial = {k: v for k, v in grown.state_dict().items() if not k.startswith("refine.1.")}
    with pytest.raises(RuntimeError, match="missing"):
        load_grown(create_model("test_trmd", refine=2), partial)  # half a refinement
    wide = create_model("test_trmd", feat_width=6, refine=1)
    with pytest.raises(RuntimeError):
        load_grown(wide, state)  # shapes differ: not a grown version of these weights


def test_refine_arguments_are_checked():
    with pytest.raises(InputError, match="refine_width"):
        create_model("test_trmd", refine=2, refine_width=1)  # below the up-step's 2 channels
    with pytest.raises(InputError, match="refine"):
        create_model("test_trmd", refine=-1)
    assert "refine" not in create_model("test_trmd").args  # older metadata stays valid


def test_macs_count_the_refinement_by_hand():
    base = create_model("test_trmd")
    net = create_model("test_trmd", refine=2, refine_width=6)
    hs, fw = net.up_width, 4  # test_trmd: widths[0] // 2 = 2 channels, feat_width 4
    h, w = 48, 64  # already a multiple of 16: no padding
    hand = h * w * 9 * ((hs + fw) * 6 + 6 * hs)
    assert count_macs(net, h, w) - count_macs(base, h, w) == hand


def test_weights_round_trip_keeps_the_refinement(tmp_path):
    net = _trained_like(refine=2, refine_width=3)
    path = save_weights(tmp_path / "w.safetensors", net, half=False)
    back, meta = load_weights(path)
    assert back.args["refine"] == 2 and back.args["refine_width"] == 3
    x = RENetInputs(*_inputs())
    with torch.no_grad():
        torch.testing.assert_close(back(x), net(x))


def test_training_grows_a_network_from_a_run_without_refinement(tmp_path):
    data = make_gopro_h5(tmp_path / "g.h5", k=12)
    train([data], recipe=recipe("train.steps=2", "train.val_every=2"), run_dir=tmp_path / "a")
    grow = apply_overrides(recipe(), ["model.args={refine=2}", "optim.lr=1e-12",
                                      "optim.min_lr=0.0", "train.steps=1", "train.val_every=1"])
    res = train([data], recipe=grow, run_dir=tmp_path / "b",
                init_weights=tmp_path / "a" / "checkpoint.safetensors")
    assert any("refine" in n and "identity" in n for n in res.notes)
    a = load_file(str(tmp_path / "a" / "checkpoint.safetensors"))
    b = load_file(str(tmp_path / "b" / "checkpoint.safetensors"))
    assert any(k.startswith("model/refine.") for k in b)
    for k, v in a.items():  # every old tensor carried over (a step at lr 1e-12 moves nothing)
        if k.startswith("model/") and v.is_floating_point() and "running" not in k:
            torch.testing.assert_close(b[k], v, atol=1e-6, rtol=0, msg=k)
