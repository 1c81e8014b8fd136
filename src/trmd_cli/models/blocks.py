"""RE-Net's building blocks: channel attention, the cross-modal fusion blocks, convolutions.

The fusion blocks follow the paper (K. Chen and L. Yu, TMM 2024, Sec. III); see
:mod:`trmd_cli.models.renet` for how they are put together and where they depart from it.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ..errors import InputError, check_shape

__all__ = [
    "ATTN_NORMS",
    "NORMS",
    "channel_attention_logits",
    "channel_cross_attention",
    "ChannelAttention",
    "PointwiseConv",
    "ResBlock",
    "FeatureExtractor",
    "CrossChannelBlock",
    "SpatialFusionBlock",
    "Refinement",
    "NoRefinement",
    "conv_act",
    "up_act",
]

#: how the C×C attention logits are scaled (see :func:`channel_attention_logits`)
ATTN_NORMS = ("none", "spatial", "l2")
#: normalisation layers inside the network
NORMS = ("batch", "none")


def channel_attention_logits(key: torch.Tensor, query: torch.Tensor, norm: str) -> torch.Tensor:
    """C×C attention logits between the channels of ``key`` and ``query``.

    Args:
        key, query: (B, C, H, W).
        norm: ``"none"`` — K·Qᵀ/√C as in the paper: a sum over H·W pixels, so the logits grow
            with the image area and differ between training crops and full frames;
            ``"spatial"`` — additionally divided by H·W (a mean over pixels);
            ``"l2"`` — each channel's H·W vector L2-normalised first (cosine similarity, as in
            Restormer), also divided by √C.
    Returns:
        (B, C, C) logits; row i attends over the query channels j.
    Raises:
        ShapeError: key and query differ in shape.
    """
    check_shape(key, ("B", "C", "H", "W"), "key")
    check_shape(query, tuple(key.shape), "query")
    b, c, h, w = key.shape
    k = key.reshape(b, c, h * w)
    q = query.reshape(b, c, h * w)
    if norm == "l2":
        k = F.normalize(k, dim=-1)
        q = F.normalize(q, dim=-1)
    logits = torch.matmul(k, q.transpose(-2, -1)) * (c ** -0.5)
    if norm == "spatial":
        logits = logits / (h * w)
    elif norm not in ("none", "l2"):
        raise InputError(f"attn_norm {norm!r} is not one of {', '.join(ATTN_NORMS)}")
    return logits


def channel_cross_attention(key: torch.Tensor, query: torch.Tensor, value: torch.Tensor,
                            norm: str = "none",
                            temperature: torch.Tensor | float = 1.0) -> torch.Tensor:
    """softmax(temperature · logits(K, Q)) · V, mixing the channels of ``value``.

    Args:
        key, query, value: (B, C, H, W).
        norm: see :func:`channel_attention_logits`.
        temperature: scalar multiplying the logits (learned in the normalised variants).
    Returns:
        (B, C, H, W).
    """
    check_shape(value, tuple(key.shape), "value")
    b, c, h, w = value.shape
    # the logits sum over all H·W pixels: in float16 (mixed precision on CUDA) a full frame
    # overflows, so they and the softmax stay in float32 whatever the autocast
    wide = (torch.float32, torch.float64)
    with torch.autocast(device_type=key.device.type, enabled=False):
        logits = channel_attention_logits(key if key.dtype in wide else key.float(),
                                          query if query.dtype in wide else query.float(), norm)
        attn = (logits * temperature).softmax(dim=-1)
    return torch.matmul(attn.to(value.dtype), value.reshape(b, c, h * w)).reshape(b, c, h, w)


class ChannelAttention(nn.Module):
    """Module form of :func:`channel_cross_attention` (holds ``norm`` and the temperature).

    Args:
        norm: one of :data:`ATTN_NORMS`. The normalised variants (``"spatial"``, ``"l2"``)
            learn a scalar temperature, initialised to 1, since their logits start small.
    """

    def __init__(self, norm: str = "none") -> None:
        super().__init__()
        if norm not in ATTN_NORMS:
            raise InputError(f"attn_norm {norm!r} is not one of {', '.join(ATTN_NORMS)}")
        self.norm = norm
        self.temperature = nn.Parameter(torch.ones(())) if norm != "none" else None

    def forward(self, key: torch.Tensor, query: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
        t = 1.0 if self.temperature is None else self.temperature
        return channel_cross_attention(key, query, value, self.norm, t)

    def extra_repr(self) -> str:
        return f"norm={self.norm!r}"


class PointwiseConv(nn.Conv2d):
    """1×1 convolution computed as one matrix product.

    Same parameters and state-dict keys as ``nn.Conv2d(cin, cout, 1)``; on CPU PyTorch runs
    1×1 convs through a slow im2col path, while the product W·X over (C, H·W) is 2–4× faster.
    """

    def __init__(self, cin: int, cout: int, bias: bool = True) -> None:
        super().__init__(cin, cout, 1, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return _pointwise(x, self.weight, self.bias)


def _pointwise(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """(B, C, H, W) → (B, O, H, W) with weight (O, C[, 1, 1]): a batched W·X, no transposes."""
    b, c, h, w = x.shape
    o = weight.shape[0]
    wb = weight.reshape(1, o, c).expand(b, o, c)
    x3 = x.reshape(b, c, h * w)
    y = torch.bmm(wb, x3) if bias is None else torch.baddbmm(bias.view(1, o, 1), wb, x3)
    return y.view(b, o, h, w)


def conv_act(cin: int, cout: int, k: int, stride: int = 1) -> nn.Sequential:
    """k×k conv (same padding) + ReLU; stride 2 halves H and W."""
    return nn.Sequential(nn.Conv2d(cin, cout, k, stride, k // 2), nn.ReLU(inplace=True))


def up_act(cin: int, cout: int, k: int = 5) -> nn.Sequential:
    """k×k stride-2 transposed conv + ReLU: doubles H and W."""
    # output_padding=1 makes every up-step exactly ×2 on the padded (multiple-of-16) grid
    return nn.Sequential(nn.ConvTranspose2d(cin, cout, k, 2, k // 2, output_padding=1),
                         nn.ReLU(inplace=True))


def _proj_norm_act(cin: int, cout: int, norm: str) -> nn.Sequential:
    """1×1 conv [+ BatchNorm] + ReLU: the query/key projections of the CCB."""
    if norm == "batch":
        return nn.Sequential(PointwiseConv(cin, cout, bias=False), nn.BatchNorm2d(cout),
                             nn.ReLU(inplace=True))
    return nn.Sequential(PointwiseConv(cin, cout), nn.ReLU(inplace=True))


class ResBlock(nn.Module):
    """x → ReLU(x + conv3×3[-BN]-ReLU-conv3×3[-BN](x)).

    Args:
        channels: feature channels.
        norm: ``"batch"`` (paper) or ``"none"`` (convs get biases instead).
    """

    def __init__(self, channels: int, norm: str = "batch") -> None:
        super().__init__()
        bn = norm == "batch"
        layers: list[nn.Module] = [nn.Conv2d(channels, channels, 3, 1, 1, bias=not bn)]
        if bn:
            layers.append(nn.BatchNorm2d(channels))
        layers += [nn.ReLU(inplace=True), nn.Conv2d(channels, channels, 3, 1, 1, bias=not bn)]
        if bn:
            layers.append(nn.BatchNorm2d(channels))
        self.body = nn.Sequential(*layers)
        self.act = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(x + self.body(x))


class FeatureExtractor(nn.Module):
    """Two 5×5 conv + ReLU: (B, cin, H, W) → (B, cout, H, W), cout/2 channels in between."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.conv1 = conv_act(cin, max(cout // 2, 1), 5)
        self.conv2 = conv_act(max(cout // 2, 1), cout, 5)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv2(self.conv1(x))


class CrossChannelBlock(nn.Module):
    """CCB: dual-branch cross-modal channel attention with residual connections.

    Branch m ∈ {blur, event}: out_m = x_m + P_m(softmax(K_m(x_m)·Q_o(x_o)ᵀ)·V_m(x_m)), o the other
    modality; K, Q are 1×1 conv [+BN] + ReLU, V and P plain 1×1 convs.

    Args:
        dim: channels of each modality's features.
        norm: ``"batch"`` or ``"none"`` in the query/key projections.
        attn_norm: scaling of the attention logits, one of :data:`ATTN_NORMS`.
    """

    def __init__(self, dim: int, norm: str = "batch", attn_norm: str = "none") -> None:
        super().__init__()
        self.blur_q = _proj_norm_act(dim, dim, norm)
        self.blur_k = _proj_norm_act(dim, dim, norm)
        self.blur_v = PointwiseConv(dim, dim)
        self.blur_proj = PointwiseConv(dim, dim)
        self.event_q = _proj_norm_act(dim, dim, norm)
        self.event_k = _proj_norm_act(dim, dim, norm)
        self.event_v = PointwiseConv(dim, dim)
        self.event_proj = PointwiseConv(dim, dim)
        self.blur_attn = ChannelAttention(attn_norm)
        self.event_attn = ChannelAttention(attn_norm)

    def forward(self, blur: torch.Tensor,
                event: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        qb, qe = self.blur_q(blur), self.event_q(event)
        b = self.blur_attn(self.blur_k(blur), qe, self.blur_v(blur))
        e = self.event_attn(self.event_k(event), qb, self.event_v(event))
        return blur + self.blur_proj(b), event + self.event_proj(e)


class SpatialFusionBlock(nn.Module):
    """SFB: F = w_b·S_b + w_e·S_e with (w_b, w_e) = softmax over the two modalities of two
    1×1 convs g_b, g_e of [S_b, S_e] — a weight per pixel and channel.

    A softmax over two entries is w_b = sigmoid(g_b − g_e), and g_b − g_e is one 1×1 conv whose
    weights are the difference of the two: that is how it is computed (same parameters, a third
    of the full-resolution work of two convs, a stack and a softmax).

    Args:
        dim: channels of each input (and of the output).
    """

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.gate_blur = PointwiseConv(2 * dim, dim)
        self.gate_event = PointwiseConv(2 * dim, dim)

    def forward(self, blur: torch.Tensor, event: torch.Tensor) -> torch.Tensor:
        both = torch.cat([blur, event], 1)
        w_blur = torch.sigmoid(_pointwise(both, self.gate_blur.weight - self.gate_event.weight,
                                          self.gate_blur.bias - self.gate_event.bias))
        return event + w_blur * (blur - event)


class Refinement(nn.ModuleList):
    """3×3 conv + ReLU layers at full resolution between the last up-step and the head.

    The first sees [up-step output, fused features]; the last returns to the up-step's width for
    the head. The paper's U-Net has no skip at full resolution, so without this every per-pixel
    detail passes through the stride-2 encoder.

    Args:
        up_width: channels of the up-step's output (and of this block's output).
        fused_width: channels of the fused features.
        layers: number of convolutions, ≥ 1.
        width: channels between them, ≥ ``up_width``.
    """

    def __init__(self, up_width: int, fused_width: int, layers: int, width: int) -> None:
        ins = [up_width + fused_width] + [width] * (layers - 1)
        outs = [width] * (layers - 1) + [up_width]
        super().__init__([conv_act(i, o, 3) for i, o in zip(ins, outs)])
        self.up_width = up_width

    def forward(self, up: torch.Tensor, fused: torch.Tensor) -> torch.Tensor:
        x = torch.cat([up, fused], 1)
        for layer in self:
            x = layer(x)
        return x

    def init_identity(self) -> None:
        """Identity on the up-step's channels (they are ≥ 0 after its ReLU, so each
        conv + ReLU passes them through), zero on the fused features: the refinement starts as
        a no-op and learns from the gradient what the fused features add."""
        hs = self.up_width
        with torch.no_grad():
            for layer in self:
                conv = layer[0]
                conv.weight.zero_()
                conv.bias.zero_()
                nn.init.dirac_(conv.weight[:hs, :hs])


class NoRefinement(nn.Identity):
    """The paper's network: the up-step's output goes to the head as it is."""

    def forward(self, up: torch.Tensor, fused: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        return up
