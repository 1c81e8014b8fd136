"""RE-Net: registry, shapes, exceptions, gradients, attention normalisation, MAC counting."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from trmd_cli.errors import InputError, ShapeError
from trmd_cli.models import (
    RENet,
    RENetInputs,
    channel_attention_logits,
    channel_cross_attention,
    count_macs,
    count_params,
    create_model,
    list_models,
    variant_args,
)
from trmd_cli.models.blocks import (
    ChannelAttention,
    CrossChannelBlock,
    PointwiseConv,
    SpatialFusionBlock,
)

torch.manual_seed(0)


def _inputs(b: int, c: int, n: int, h: int, w: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, c, h, w, generator=g), torch.randn(b, 2 * n, h, w, generator=g)


# --------------------------------------------------------------------------------------------
# registry


def test_registered_variants():
    assert {"trmd_paper", "trmd_base", "trmd_small", "test_trmd"} <= set(list_models())
    assert list_models("trmd_*") == sorted(n for n in list_models() if n.startswith("trmd_"))
    for name in list_models():
        assert variant_args(name)["attn_norm"] in ("none", "spatial", "l2")


def test_paper_width_parameter_count():
    # the paper reports ≈ 19.3 M parameters for the gray model with N = 3
    params = count_params(create_model("trmd_paper"))
    assert 19.0e6 < params < 19.6e6


def test_variants_ordered_by_size():
    sizes = [count_params(create_model(n)) for n in
             ("test_trmd", "trmd_small", "trmd_base", "trmd_paper")]
    assert sizes == sorted(sizes)
    assert sizes[0] < 50_000 and 1e6 < sizes[1] < 8e6


def test_create_with_overrides():
    m = create_model("test_trmd", n=2, channels=3, attn_norm="l2")
    assert (m.n, m.channels, m.variant) == (2, 3, "test_trmd")
    assert m.args["attn_norm"] == "l2" and m.args["n"] == 2
    # args rebuild the same architecture
    clone = RENet(**m.args)
    assert clone.state_dict().keys() == m.state_dict().keys()


def test_unknown_model_names_known_ones():
    with pytest.raises(InputError, match="trmd_small"):
        create_model("trmd_huge")


@pytest.mark.parametrize("kwargs", [dict(n=0), dict(channels=2), dict(attn_norm="softmax"),
                                    dict(norm="layer"), dict(widths=(8, 8, 8))])
def test_bad_constructor_args(kwargs):
    with pytest.raises(InputError):
        create_model("test_trmd", **kwargs)


# --------------------------------------------------------------------------------------------
# shapes (cardinality), forward + backward


@pytest.mark.parametrize("h,w", [(1, 1), (16, 16), (17, 15), (37, 53), (48, 32)])
@pytest.mark.parametrize("batch", [1, 2])
def test_output_shape_any_size(h, w, batch):
    m = create_model("test_trmd").eval()
    b, v = _inputs(batch, 1, 3, h, w)
    with torch.no_grad():
        out = m(RENetInputs(b, v))
    assert out.shape == (batch, 6, 1, h, w)
    assert torch.isfinite(out).all()


@pytest.mark.parametrize("n,channels", [(1, 1), (3, 1), (2, 3)])
def test_forward_backward_odd_size(n, channels):
    # seeded: with 4-channel layers some draws leave a layer's ReLUs all dead on one input
    torch.manual_seed(n)
    m = create_model("test_trmd", n=n, channels=channels).train()
    b, v = _inputs(2, channels, n, 37, 53)
    out = m(RENetInputs(b, v))
    assert out.shape == (2, 2 * n, channels, 37, 53)
    out.square().mean().backward()
    for name, p in m.named_parameters():
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name


def test_batch_items_independent():
    # eval mode: attention and normalisation act per sample, so batching changes nothing
    m = create_model("test_trmd").eval()
    b, v = _inputs(2, 1, 3, 21, 19)
    with torch.no_grad():
        both = m(RENetInputs(b, v))
        one = m(RENetInputs(b[1:], v[1:]))
    torch.testing.assert_close(both[1:], one, atol=1e-5, rtol=1e-5)


def test_crop_keeps_top_left_alignment():
    # padding goes right/bottom, so a frame that already is a multiple of 16 is not shifted:
    # its output equals the top-left crop of the output for the frame padded by hand
    m = create_model("test_trmd").eval()
    b, v = _inputs(1, 1, 3, 32, 48)
    with torch.no_grad():
        full = m(RENetInputs(b, v))
        bp = torch.nn.functional.pad(b[..., :30, :45], (0, 3, 0, 2), mode="replicate")
        vp = torch.nn.functional.pad(v[..., :30, :45], (0, 3, 0, 2), mode="replicate")
        padded_by_hand = m(RENetInputs(bp, vp))[..., :30, :45]
        cropped = m(RENetInputs(b[..., :30, :45], v[..., :30, :45]))
    assert full.shape[-2:] == (32, 48)
    torch.testing.assert_close(cropped, padded_by_hand, atol=1e-6, rtol=1e-6)


def test_initial_residuals_near_zero():
    m = create_model("test_trmd").eval()
    b, v = _inputs(1, 1, 3, 24, 24)
    with torch.no_grad():
        assert m(RENetInputs(b, v)).abs().max() < 0.1


# --------------------------------------------------------------------------------------------
# exceptions


def test_shape_errors():
    m = create_model("test_trmd", n=3, channels=1).eval()
    b, v = _inputs(1, 1, 3, 20, 20)
    with pytest.raises(ShapeError, match="counts"):
        m(RENetInputs(b, v[:, :4]))  # 2N = 4, model wants 6
    with pytest.raises(ShapeError, match="blurry"):
        m(RENetInputs(b.repeat(1, 3, 1, 1), v))  # RGB frame into a gray model
    with pytest.raises(ShapeError, match="counts"):
        m(RENetInputs(b, v[..., :19]))
    with pytest.raises(ShapeError):
        m(RENetInputs(b[0], v[0]))  # no batch axis


# --------------------------------------------------------------------------------------------
# attention and fusion blocks


def _tile(x: torch.Tensor, ry: int, rx: int) -> torch.Tensor:
    return x.repeat(1, 1, ry, rx)


def test_logits_scale_with_area_only_without_normalisation():
    g = torch.Generator().manual_seed(1)
    k = torch.rand(2, 5, 6, 7, generator=g, dtype=torch.float64)
    q = torch.rand(2, 5, 6, 7, generator=g, dtype=torch.float64)
    kt, qt = _tile(k, 2, 3), _tile(q, 2, 3)  # 6× the area, same content
    none, none_t = channel_attention_logits(k, q, "none"), channel_attention_logits(kt, qt, "none")
    torch.testing.assert_close(none_t, 6 * none)
    for norm in ("spatial", "l2"):
        torch.testing.assert_close(channel_attention_logits(kt, qt, norm),
                                   channel_attention_logits(k, q, norm))


def test_logits_hand_computed():
    # C = 1, two pixels: K = [1, 2], Q = [3, 4] → K·Qᵀ = 11; /√1; spatial: /2; l2: 11/(√5·5)
    k = torch.tensor([1.0, 2.0], dtype=torch.float64).reshape(1, 1, 1, 2)
    q = torch.tensor([3.0, 4.0], dtype=torch.float64).reshape(1, 1, 1, 2)
    assert channel_attention_logits(k, q, "none").item() == pytest.approx(11.0)
    assert channel_attention_logits(k, q, "spatial").item() == pytest.approx(5.5)
    assert channel_attention_logits(k, q, "l2").item() == pytest.approx(11 / (5 ** 0.5 * 5))
    with pytest.raises(InputError):
        channel_attention_logits(k, q, "softmax")


@pytest.mark.parametrize("attn_norm", ["spatial", "l2"])
def test_ccb_output_invariant_to_tiling_when_normalised(attn_norm):
    torch.manual_seed(2)
    ccb = CrossChannelBlock(6, attn_norm=attn_norm).eval()
    b, e = torch.rand(1, 6, 5, 4), torch.randn(1, 6, 5, 4)
    with torch.no_grad():
        small = ccb(b, e)
        big = ccb(_tile(b, 3, 3), _tile(e, 3, 3))
    for s, t in zip(small, big, strict=True):
        torch.testing.assert_close(t, _tile(s, 3, 3), atol=1e-5, rtol=1e-5)


def test_ccb_output_depends_on_area_without_normalisation():
    torch.manual_seed(2)
    ccb = CrossChannelBlock(6, attn_norm="none").eval()
    b, e = torch.rand(1, 6, 5, 4), torch.randn(1, 6, 5, 4)
    with torch.no_grad():
        small = ccb(b, e)
        big = ccb(_tile(b, 3, 3), _tile(e, 3, 3))
    assert (big[0] - _tile(small[0], 3, 3)).abs().max() > 1e-3


def test_attention_mixes_channels_convexly():
    # softmax rows sum to 1: a value identical in every channel comes out unchanged
    g = torch.Generator().manual_seed(3)
    k, q = torch.randn(1, 4, 3, 3, generator=g), torch.randn(1, 4, 3, 3, generator=g)
    v = torch.randn(1, 1, 3, 3, generator=g).expand(1, 4, 3, 3)
    for norm in ("none", "spatial", "l2"):
        torch.testing.assert_close(channel_cross_attention(k, q, v, norm), v)


@pytest.mark.parametrize("norm", ["none", "spatial", "l2"])
def test_attention_function_matches_module(norm):
    g = torch.Generator().manual_seed(4)
    k, q, v = (torch.randn(2, 3, 4, 5, generator=g) for _ in range(3))
    mod = ChannelAttention(norm)
    if mod.temperature is not None:
        with torch.no_grad():
            mod.temperature.fill_(1.7)
    t = 1.0 if mod.temperature is None else 1.7
    torch.testing.assert_close(mod(k, q, v), channel_cross_attention(k, q, v, norm, t))


@pytest.mark.parametrize("norm", ["none", "spatial", "l2"])
def test_attention_gradcheck(norm):
    g = torch.Generator().manual_seed(5)
    args = [torch.randn(1, 3, 2, 3, generator=g, dtype=torch.float64, requires_grad=True)
            for _ in range(3)]
    assert torch.autograd.gradcheck(lambda k, q, v: channel_cross_attention(k, q, v, norm),
                                    args)


def test_sfb_equals_softmax_of_two_convs():
    # the paper's form, written out: softmax over the modalities of two 1×1 convs
    torch.manual_seed(7)
    sfb = SpatialFusionBlock(4)
    b, e = torch.randn(2, 4, 5, 6, dtype=torch.float64), torch.randn(2, 4, 5, 6,
                                                                     dtype=torch.float64)
    sfb = sfb.double()
    both = torch.cat([b, e], 1)
    g = torch.stack([F.conv2d(both, sfb.gate_blur.weight, sfb.gate_blur.bias),
                     F.conv2d(both, sfb.gate_event.weight, sfb.gate_event.bias)]).softmax(0)
    torch.testing.assert_close(sfb(b, e), g[0] * b + g[1] * e)


def test_pointwise_conv_equals_conv2d():
    torch.manual_seed(8)
    for bias in (True, False):
        pw = PointwiseConv(5, 3, bias=bias)
        x = torch.randn(2, 5, 7, 4)
        torch.testing.assert_close(pw(x), F.conv2d(x, pw.weight, pw.bias))


def test_sfb_is_a_convex_mix():
    torch.manual_seed(6)
    sfb = SpatialFusionBlock(5)
    x = torch.randn(2, 5, 7, 6)
    torch.testing.assert_close(sfb(x, x), x)  # equal inputs: any weights give them back
    a, b = torch.zeros(1, 5, 4, 4), torch.ones(1, 5, 4, 4)
    out = sfb(a, b)  # = w_e, strictly between 0 and 1
    assert (out > 0).all() and (out < 1).all()


# --------------------------------------------------------------------------------------------
# MAC counting


def _expected_macs(args: dict, h: int, w: int) -> int:
    """Layer-by-layer count from the architecture description, at the padded size."""
    hp, wp = -(-h // 16) * 16, -(-w // 16) * 16
    px = hp * wp
    c, m, fw = args["channels"], 2 * args["n"], args["feat_width"]
    w0, w1, w2, w3 = args["widths"]
    half = fw // 2
    total = px * 25 * (half * c + fw * half) + px * 25 * (half * m + fw * half)  # extraction
    total += 8 * px * fw * fw + 2 * 2 * fw * fw * px  # CCB: 8 1×1 convs, 2 × (K·Qᵀ, A·V)
    total += px * 2 * fw * fw  # SFB: one conv of the gates' difference
    total += 25 * (px // 4 * w0 * fw + px // 16 * w1 * w0 + px // 64 * w2 * w1
                   + px // 256 * w3 * w2)  # downs (output-based)
    total += args["num_res_blocks"] * 2 * (px // 256) * w3 * w3 * 9
    total += 25 * (px // 256 * w3 * w2 + px // 64 * 2 * w2 * w1 + px // 16 * 2 * w1 * w0
                   + px // 4 * 2 * w0 * (w0 // 2))  # ups (input-based)
    total += px * (w0 // 2 + c + m) * m * c  # head
    return total


@pytest.mark.parametrize("h,w", [(32, 48), (37, 53)])
@pytest.mark.parametrize("channels", [1, 3])
def test_count_macs_matches_hand_count(h, w, channels):
    m = create_model("test_trmd", channels=channels, feat_width=6)
    assert count_macs(m, h, w) == _expected_macs(m.args, h, w)
    assert m.training  # count_macs restores the mode
