"""Growing a trained RE-Net wider (``models.grow.load_grown`` with a narrower U-Net): the wide
network computes exactly what the narrow weights computed, the new channels learn from the
first step, and a training run can start a wider network from a narrower run."""

from __future__ import annotations

import pytest
import torch
from safetensors.torch import load_file

from tests.helpers.training import make_gopro_h5, recipe
from tests.helpers.training import net_inputs as _inputs
from tests.helpers.training import trained_like as _trained_like
from trmd_cli.models import RENetInputs, create_model
from trmd_cli.models.grow import Grown, load_grown
from trmd_cli.train.loop import train
from trmd_cli.train.recipe import apply_overrides

WIDE = dict(widths=(6, 12, 12, 10))


@pytest.mark.parametrize("kw", [
    {},
    {"prior": "edi_c", "refine": 2, "refine_width": 4},
    {"prior": "edi_c", "refine": 3, "refine_width": 5, "timing": True},
])
def test_wider_network_computes_what_the_narrow_weights_computed(kw):
    old = _trained_like(**kw)
    wide_kw = {**kw, **WIDE}
    if "refine_width" in kw:
        wide_kw["refine_width"] = kw["refine_width"] + 2
    new = create_model("test_trmd", **wide_kw).eval()
    grown = load_grown(new, old.state_dict())
    assert "down1.0.weight" in grown.names and "head.weight" in grown.names
    # every U-Net tensor really is larger, and the old values sit inside it
    assert new.down4[0].weight.shape[0] == 10 > old.down4[0].weight.shape[0]
    blurry, voxels = _inputs()
    levels = voxels + 0.5 * torch.rand_like(voxels) if kw.get("timing") else None
    x = RENetInputs(blurry, voxels, levels=levels, contrast=0.3)
    with torch.no_grad():
        a, b = old(x), new(x)
    torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-6)
    assert a.abs().max() > 1e-2  # a non-trivial output was compared


def test_new_channels_carry_signal_and_their_zero_weights_learn():
    old = _trained_like()
    new = create_model("test_trmd", **WIDE).train()
    load_grown(new, old.state_dict())
    blurry, voxels = _inputs()
    new(RENetInputs(blurry, voxels)).square().mean().backward()
    w = new.down2[0]
    old_out, old_in = old.down2[0].weight.shape[:2]
    # weights from the new channels of down1 into the old ones of down2: zero, with a gradient
    assert torch.count_nonzero(w.weight[:old_out, old_in:]) == 0
    assert w.weight.grad[:old_out, old_in:].abs().sum() > 0
    # the new output channels start random (not zero): they carry signal forward
    assert w.weight[old_out:].abs().sum() > 0


def test_narrower_or_other_networks_are_refused():
    wide = _trained_like(**WIDE)
    with pytest.raises(RuntimeError):
        load_grown(create_model("test_trmd"), wide.state_dict())  # shrinking is not growing
    with pytest.raises(RuntimeError):
        load_grown(create_model("test_trmd", feat_width=6, **WIDE), _trained_like().state_dict())


def test_training_starts_a_wider_network_from_a_narrower_run(tmp_path):
    data = make_gopro_h5(tmp_path / "g.h5", k=12)
    train([data], recipe=recipe("train.steps=2", "train.val_every=2"), run_dir=tmp_path / "a")
    a_res = load_file(str(tmp_path / "a" / "checkpoint.safetensors"))
    grow = apply_overrides(recipe(), ["model.args={widths=[6, 12, 12, 10]}", "optim.lr=1e-12",
                                      "optim.min_lr=0.0", "train.steps=1", "train.val_every=1"])
    res = train([data], recipe=grow, run_dir=tmp_path / "b",
                init_weights=tmp_path / "a" / "checkpoint.safetensors")
    assert any("narrower U-Net" in n for n in res.notes)
    assert not any("identity" in n for n in res.notes)
    b = load_file(str(tmp_path / "b" / "checkpoint.safetensors"))
    assert b["model/down4.0.weight"].shape[0] == 10
    old = a_res["model/down1.0.weight"]
    torch.testing.assert_close(b["model/down1.0.weight"][:old.shape[0]], old, atol=1e-9, rtol=0)


def test_weights_that_fit_grow_nothing():
    old = _trained_like(prior="edi_c", refine=2, timing=True)
    new = create_model("test_trmd", prior="edi_c", refine=2, timing=True)
    grown = load_grown(new, old.state_dict())
    assert grown == Grown() and grown.names == []
    for k, v in old.state_dict().items():
        assert torch.equal(new.state_dict()[k], v), k
