"""What RE-Net is given (``models.inputs``): the inputs dataclass, what each network needs, and
the input encoders chosen when it is built."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from trmd_cli.errors import InputError, ShapeError
from trmd_cli.models import RENetInputs, RENetNeeds, create_model
from trmd_cli.models.blocks import NoRefinement, Refinement
from trmd_cli.models.inputs import (
    EdiPriorInputs,
    GivenContrastEdiPriorInputs,
    PlainInputs,
    TimingInputs,
    build_encoder,
)
from trmd_cli.models.prior import edi_prior


def _batch(b: int = 2, n: int = 3, c: int = 1, h: int = 13, w: int = 22, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(-4, 5, (b, 2 * n, h, w), generator=g).float()
    return (torch.rand(b, c, h, w, generator=g), counts,
            counts + torch.rand(counts.shape, generator=g) - 0.5)


def test_inputs_are_frozen_and_padded_without_shifting():
    blurry, counts, levels = _batch()
    x = RENetInputs(blurry, counts, levels=levels, contrast=0.3)
    with pytest.raises(dataclasses.FrozenInstanceError):
        x.contrast = 0.2  # type: ignore[misc]
    p = x.padded(16)
    assert p.blurry.shape == (2, 1, 16, 32) and p.counts.shape == p.levels.shape == (2, 6, 16, 32)
    assert p.contrast == 0.3
    torch.testing.assert_close(p.counts[..., :13, :22], counts, rtol=0, atol=0)
    torch.testing.assert_close(p.levels[..., 15, 31], levels[..., 12, 21], rtol=0, atol=0)
    assert p.padded(16) is p  # already a multiple: the same inputs
    assert RENetInputs(blurry, counts).padded(16).levels is None


def test_what_each_variant_needs_and_which_encoder_it_gets():
    cases = {
        "trmd_paper": (RENetNeeds(), PlainInputs),
        "trmd_small": (RENetNeeds(), PlainInputs),
        "trmd_small_edi": (RENetNeeds(), EdiPriorInputs),
        "trmd_small_edi_c": (RENetNeeds(contrast=True), GivenContrastEdiPriorInputs),
        "trmd_small_prior": (RENetNeeds(contrast=True, timing=True), TimingInputs),
    }
    for name, (needs, cls) in cases.items():
        net = create_model(name, feat_width=2, widths=(2, 4, 4, 4), num_res_blocks=1,
                           **({"refine_width": 2} if name == "trmd_small_prior" else {}))
        assert net.needs == needs and type(net.encoder) is cls, name
    shipped = create_model("trmd_small_prior", feat_width=2, widths=(2, 4, 4, 4),
                           num_res_blocks=1, refine_width=2)
    assert isinstance(shipped.encoder.prior, GivenContrastEdiPriorInputs)
    assert isinstance(shipped.refine, Refinement) and len(shipped.refine) == 3
    assert isinstance(create_model("test_trmd").refine, NoRefinement)
    with pytest.raises(dataclasses.FrozenInstanceError):
        shipped.needs.timing = False  # type: ignore[misc]


def test_encoders_add_no_weights():
    # the state-dict keys are those every weights file was written with
    for kw in ({}, {"prior": "edi"}, {"prior": "edi_c", "timing": True, "refine": 2}):
        net = create_model("test_trmd", **kw)
        assert not list(net.encoder.state_dict())
        assert not any(k.startswith("encoder.") for k in net.state_dict())
    keys = set(create_model("test_trmd", refine=2).state_dict())
    assert {"refine.0.0.weight", "refine.1.0.bias", "head.weight"} <= keys


def test_encoded_channels_and_parts_by_hand():
    blurry, counts, levels = _batch(b=2, n=2, c=3, h=16, w=16)
    ladder = (0.1, 0.2, 0.4)
    c = torch.tensor([0.2, 0.3])
    x = RENetInputs(blurry, counts, levels=levels, contrast=c)
    plain = build_encoder(2, 3)(x)
    assert plain.blur is blurry and plain.event is counts and plain.head == (blurry, counts)
    enc = build_encoder(2, 3, "edi_c", ladder, timing=True)
    out = enc(x)
    assert out.blur.shape[1] == enc.blur_channels == 3 * (1 + 3) + 3
    assert out.event.shape[1] == enc.event_channels == 4 * (1 + 3 * 3) + 4 * (1 + 3)
    assert sum(t.shape[1] for t in out.head) == enc.blur_channels + enc.event_channels
    # the levels' EDI at the ladder's second rung, each sample at its own c
    mid, res = edi_prior(blurry, levels, c[:, None] * 0.2)
    torch.testing.assert_close(out.blur[:, -3:], mid.flatten(1, 2), rtol=0, atol=0)
    torch.testing.assert_close(out.event[:, -4 * 3:], res.flatten(1, 3), rtol=0, atol=0)
    # EDI's residuals at the second rung sit where the head's identity starts
    _, res_c = edi_prior(blurry, counts, c[:, None] * torch.tensor(ladder)[None])
    heads = torch.cat(out.head, 1)
    at = enc.edi_at
    torch.testing.assert_close(heads[:, at:at + 4 * 3], res_c[:, 1].flatten(1, 2), rtol=0,
                               atol=0)


def test_networks_ignore_inputs_they_do_not_take():
    blurry, counts, levels = _batch()
    for net in (create_model("test_trmd").eval(), create_model("test_trmd", prior="edi").eval()):
        with torch.no_grad():
            bare = net(RENetInputs(blurry, counts))
            given = net(RENetInputs(blurry, counts, levels=levels, contrast=0.3))
        torch.testing.assert_close(given, bare, rtol=0, atol=0)


def test_missing_or_bad_inputs_are_named():
    blurry, counts, levels = _batch()
    net = create_model("test_trmd", prior="edi_c", timing=True).eval()
    with pytest.raises(InputError, match="sub-bin timing") as e:
        net(RENetInputs(blurry, counts, contrast=0.2))
    assert "`levels`" in e.value.hint
    with pytest.raises(InputError, match="contrast threshold") as e:
        net(RENetInputs(blurry, counts, levels=levels))
    assert "`contrast`" in e.value.hint and "--" not in e.value.hint
    with pytest.raises(ShapeError, match="levels"):
        net(RENetInputs(blurry, counts, levels=levels[..., :12, :], contrast=0.2))
    with pytest.raises(InputError, match="positive"):
        net(RENetInputs(blurry, counts, levels=levels, contrast=float("nan")))
    with pytest.raises(ShapeError, match="counts"):
        net(RENetInputs(blurry, counts[:, :4], levels=levels[:, :4], contrast=0.2))
    with pytest.raises(InputError, match="timing needs a prior"):
        build_encoder(3, 1, "none", (), timing=True)
