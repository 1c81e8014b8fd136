"""RE-Net: the residual-estimation network of TRMD.

Paper: K. Chen and L. Yu, "Motion Deblur by Learning Residual from Events", IEEE Transactions on
Multimedia, 2024 (official code: github.com/chenkang455/TRMD). Written from the paper's
description; no code or weights of the official repository are included, so no weight licence
applies here. Weights trained by this project are described by their safetensors metadata.

From a blurry frame B (B, C, H, W) and SCER voxels V (B, 2N, H, W) the network predicts the 2N
residuals R(k) = L(k) − L(N), k ≠ N, of each colour channel: (B, 2N, C, H, W). The latent frames
then follow in closed form (:func:`trmd_cli.reconstruct.reconstruct`, Eq. 11–12).

Structure (paper, Sec. III):

1. Feature extraction: two 5×5 conv + ReLU per modality.
2. Fusion: the cross-modal channel block (CCB) — two branches of C×C channel attention, each
   taking its keys and values from one modality and its queries from the other, added back to
   its input — then the spatial fusion block (SFB): two 1×1 convs over both outputs give
   per-pixel, per-channel weights, softmax-normalised across the two modalities, that mix them.
3. Residual estimation: a U-Net with four stride-2 5×5 convs, residual blocks at the bottom,
   four stride-2 5×5 transposed convs with skip connections, and a 1×1 head over
   [decoder features, B, V].

``refine`` (a departure, off in the paper's variant) adds 3×3 convs at full resolution between
the last up-step and the head, over [decoder features, fused features]: the paper's U-Net has
no skip at full resolution, so every per-pixel detail passes through the stride-2 encoder; on
simulated data most of the remaining error is in that fine detail.

Departures from the official code, deliberate: the SFB softmax runs over the two modalities
(as the paper writes) rather than over the 2C concatenated channels; each CCB branch has its own
output projection (the official code reuses the blur one); no dropout in the query/key
projections. ``attn_norm`` adds size-independent attention (see :func:`channel_attention_logits`).

Any H×W is accepted: inputs are replicate-padded to a multiple of 16 and the output cropped back.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from ..errors import InputError, ShapeError, check_shape
from .prior import DEFAULT_CONTRASTS, RELATIVE_CONTRASTS, edi_prior
from .registry import register_model

__all__ = [
    "RENet",
    "ATTN_NORMS",
    "NORMS",
    "PRIORS",
    "channel_attention_logits",
    "channel_cross_attention",
    "ChannelAttention",
    "CrossChannelBlock",
    "SpatialFusionBlock",
    "PointwiseConv",
    "count_macs",
    "count_params",
    "variant_args",
    "trmd_paper",
    "trmd_base",
    "trmd_small",
    "trmd_small_edi",
    "trmd_small_edi_c",
    "trmd_small_edi_c_fr",
    "trmd_small_edi_c_fr_t",
    "test_trmd",
]

#: how the C×C attention logits are scaled (see :func:`channel_attention_logits`)
ATTN_NORMS = ("none", "spatial", "l2")
#: normalisation layers inside the network
NORMS = ("batch", "none")
#: physical priors the network can be given besides B and V (see :mod:`trmd_cli.models.prior`)
PRIORS = ("none", "edi", "edi_c")
#: number of stride-2 stages; inputs are padded to a multiple of 2**_DOWNS
_DOWNS = 4


# --------------------------------------------------------------------------------------------
# Building blocks


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


def _conv_act(cin: int, cout: int, k: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, k, stride, k // 2), nn.ReLU(inplace=True))


def _up_act(cin: int, cout: int, k: int = 5) -> nn.Sequential:
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
        self.conv1 = _conv_act(cin, max(cout // 2, 1), 5)
        self.conv2 = _conv_act(max(cout // 2, 1), cout, 5)

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


# --------------------------------------------------------------------------------------------
# The model


class RENet(nn.Module):
    """Residual-estimation network: (blurry, SCER voxels) → residuals R(k) = L(k) − L(N).

    Args:
        n: N; the voxels have 2N channels and 2N residuals are predicted per colour channel.
        channels: colour channels of the frame: 1 (gray) or 3 (RGB). Voxels are shared.
        feat_width: channels of each modality's extracted features (paper: 32).
        widths: channels of the four encoder stages (paper: 64, 128, 256, 512).
        num_res_blocks: residual blocks at the bottom of the U-Net (paper: 2).
        norm: ``"batch"`` (paper) or ``"none"``: normalisation in residual blocks and the CCB's
            query/key projections.
        attn_norm: CCB logit scaling, one of :data:`ATTN_NORMS` (paper: ``"none"``).
        prior: ``"none"`` (paper) or ``"edi"``: EDI's middle frame and residuals, computed from
            B and V for each contrast of ``prior_contrasts`` (:func:`~trmd_cli.models.prior.
            edi_prior`), join B's and V's inputs to the feature extractors and to the head, and
            the head starts out returning EDI's residuals at ``prior_contrasts[1]`` — training
            begins at EDI's quality and learns the correction. A departure from the paper.
            ``"edi_c"``: the same, with the ladder scaled by a contrast threshold given with
            every frame (``forward(..., contrast=c)``; :attr:`needs_contrast`).
        prior_contrasts: the contrast ladder of the prior (log-intensity per event); for
            ``"edi_c"``, multiples of the given threshold.
        refine: number of 3×3 conv + ReLU layers at full resolution before the head (paper: 0).
            The first sees the last up-step's output and the fused features; they start as an
            identity on the up-step's output, so weights trained without them carry over
            exactly (:meth:`load_grown`).
        refine_width: channels inside the refinement (default and minimum: the last
            up-step's, ``widths[0] // 2``); its last layer returns to that width for the head.
        timing: the voxels carry 2N more channels after the SCER counts: the same instants
            with sub-bin timing kept (:func:`~trmd_cli.voxel.scer_levels`), and the network
            also sees EDI computed from them at the ladder's second rung. Needs a prior. Their
            weights start at zero, so weights trained without them carry over exactly
            (:meth:`load_grown`).

    Shapes:
        blurry (B, C, H, W), voxels (B, 2N, H, W) (with ``timing``: (B, 4N, H, W), counts
        then levels) → residuals (B, 2N, C, H, W), any H, W ≥ 1.

    Example::

        >>> from trmd_cli.models import create_model
        >>> import torch
        >>> net = create_model("test_trmd").eval()
        >>> net(torch.rand(1, 1, 37, 53), torch.randn(1, 6, 37, 53)).shape
        torch.Size([1, 6, 1, 37, 53])
    """

    def __init__(self, n: int = 3, channels: int = 1, feat_width: int = 32,
                 widths: Sequence[int] = (64, 128, 256, 512), num_res_blocks: int = 2,
                 norm: str = "batch", attn_norm: str = "none", prior: str = "none",
                 prior_contrasts: Sequence[float] | None = None, refine: int = 0,
                 refine_width: int | None = None, timing: bool = False) -> None:
        super().__init__()
        widths = tuple(int(w) for w in widths)
        if n < 1:
            raise InputError(f"N must be ≥ 1, got {n}")
        if channels not in (1, 3):
            raise InputError(f"channels must be 1 (gray) or 3 (RGB), got {channels}")
        if len(widths) != _DOWNS or min(widths) < 2 or feat_width < 1:
            raise InputError(f"widths must be {_DOWNS} integers ≥ 2 and feat_width ≥ 1, got "
                             f"{widths}, {feat_width}")
        if norm not in NORMS:
            raise InputError(f"norm {norm!r} is not one of {', '.join(NORMS)}")
        if attn_norm not in ATTN_NORMS:
            raise InputError(f"attn_norm {attn_norm!r} is not one of {', '.join(ATTN_NORMS)}")
        if prior not in PRIORS:
            raise InputError(f"prior {prior!r} is not one of {', '.join(PRIORS)}")
        if prior_contrasts is None:
            prior_contrasts = RELATIVE_CONTRASTS if prior == "edi_c" else DEFAULT_CONTRASTS
        contrasts = tuple(float(c) for c in prior_contrasts)
        if prior != "none" and (len(contrasts) < 2 or min(contrasts) <= 0):
            raise InputError(f"prior_contrasts must be ≥ 2 positive thresholds, got {contrasts}")
        if timing and prior == "none":
            raise InputError("timing needs a prior (prior='edi' or 'edi_c')")
        refine = int(refine)
        if not 0 <= refine <= 8:
            raise InputError(f"refine must be 0–8 layers, got {refine}")
        hs = max(widths[0] // 2, 1)
        rw = hs if refine_width is None else int(refine_width)
        if refine and rw < hs:
            raise InputError(f"refine_width must be ≥ {hs} (the last up-step's width), got {rw}")
        #: every constructor argument, JSON-friendly: what weights metadata records
        self.args: dict[str, Any] = dict(n=n, channels=channels, feat_width=feat_width,
                                         widths=list(widths), num_res_blocks=num_res_blocks,
                                         norm=norm, attn_norm=attn_norm)
        if prior != "none":  # absent for the paper's network: older weights files stay valid
            self.args.update(prior=prior, prior_contrasts=list(contrasts))
        if refine:
            self.args.update(refine=refine, refine_width=rw)
        if timing:
            self.args.update(timing=True)
        #: registered variant name, set by the factories (None when built directly)
        self.variant: str | None = None
        self.n, self.channels = n, channels
        self.prior = prior
        self.prior_contrasts = contrasts if prior != "none" else ()
        self.timing = bool(timing)
        m = 2 * n
        k = len(self.prior_contrasts)
        w0, w1, w2, w3 = widths
        # with the prior, B travels with EDI's middle frames, V with EDI's residuals
        blur_in, event_in = channels * (1 + k), m * (1 + k * channels)
        # with timing: EDI's middle frame from the levels joins B; the levels and that EDI's
        # residuals join V — appended last everywhere, so the old weights are a slice
        self._timing_in = (channels, m * (1 + channels)) if timing else (0, 0)
        blur_in, event_in = blur_in + self._timing_in[0], event_in + self._timing_in[1]

        self.blur_fe = FeatureExtractor(blur_in, feat_width)
        self.event_fe = FeatureExtractor(event_in, feat_width)
        self.ccb = CrossChannelBlock(feat_width, norm, attn_norm)
        self.sfb = SpatialFusionBlock(feat_width)

        self.down1 = _conv_act(feat_width, w0, 5, 2)
        self.down2 = _conv_act(w0, w1, 5, 2)
        self.down3 = _conv_act(w1, w2, 5, 2)
        self.down4 = _conv_act(w2, w3, 5, 2)
        self.res = nn.Sequential(*[ResBlock(w3, norm) for _ in range(num_res_blocks)])
        self.up1 = _up_act(w3, w2)
        self.up2 = _up_act(2 * w2, w1)
        self.up3 = _up_act(2 * w1, w0)
        self.up4 = _up_act(2 * w0, max(w0 // 2, 1))
        self._head_skip = max(w0 // 2, 1)
        self.refine: nn.Sequential | None = None
        if refine:
            ins = [hs + feat_width] + [rw] * (refine - 1)
            outs = [rw] * (refine - 1) + [hs]
            self.refine = nn.Sequential(*[_conv_act(i, o, 3) for i, o in zip(ins, outs)])
        self.head = PointwiseConv(self._head_skip + blur_in + event_in, m * channels)
        self.init_weights()

    def init_weights(self) -> None:
        """PyTorch defaults, except a near-zero head: training starts from R ≈ 0, i.e. every
        latent frame ≈ B, instead of random residuals — or, with the EDI prior, from EDI's
        residuals at the second contrast of the ladder (an identity from those inputs)."""
        nn.init.normal_(self.head.weight, std=1e-3)
        nn.init.zeros_(self.head.bias)
        if self.refine is not None:
            self._init_refine()
        if self.prior != "none":
            m, c = 2 * self.n, self.channels
            # head input order: [features, B, middles (K·C), V (2N), residuals (K·2N·C)]
            first = self._head_skip + c * (1 + len(self.prior_contrasts)) + m + m * c
            with torch.no_grad():
                for j in range(m * c):
                    self.head.weight[j, first + j] += 1.0

    def _init_refine(self) -> None:
        """Identity on the up-step's channels (they are ≥ 0 after its ReLU, so each
        conv + ReLU passes them through), zero on the fused features: the refinement starts as
        a no-op and learns from the gradient what the fused features add."""
        assert self.refine is not None
        hs = self._head_skip
        with torch.no_grad():
            for layer in self.refine:
                conv = layer[0]
                conv.weight.zero_()
                conv.bias.zero_()
                nn.init.dirac_(conv.weight[:hs, :hs])

    #: parameter prefixes a model may lack in older weights: they start as an identity
    GROWN_PREFIXES = ("refine.",)
    #: weights whose input channels grow with ``timing`` (the new ones are appended, zero)
    TIMING_INPUTS = ("blur_fe.conv1.0.weight", "event_fe.conv1.0.weight", "head.weight")

    def _unet_layouts(self, old: dict[str, int]) -> dict[str, tuple[list, list]]:
        """Per U-Net module: (output, input) channel layouts as [(old, new) …] segments —
        concatenated inputs have one segment per part — for widths ``old`` → this network's."""
        own = dict(zip(("w0", "w1", "w2", "w3"), self.args["widths"]),
                   hs=self._head_skip, rw=self.args.get("refine_width", self._head_skip))
        seg = {k: (old[k], own[k]) for k in own}
        fw = self.args["feat_width"]
        feat = (fw, fw)
        out: dict[str, tuple[list, list]] = {
            "down1.0": ([seg["w0"]], [feat]), "down2.0": ([seg["w1"]], [seg["w0"]]),
            "down3.0": ([seg["w2"]], [seg["w1"]]), "down4.0": ([seg["w3"]], [seg["w2"]]),
            "up1.0": ([seg["w2"]], [seg["w3"]]),
            "up2.0": ([seg["w1"]], [seg["w2"], seg["w2"]]),
            "up3.0": ([seg["w0"]], [seg["w1"], seg["w1"]]),
            "up4.0": ([seg["hs"]], [seg["w0"], seg["w0"]]),
        }
        for i in range(len(self.res)):
            for j in (0, 1, 3, 4):
                out[f"res.{i}.body.{j}"] = ([seg["w3"]], [seg["w3"]])
        if self.refine is not None:
            k = len(self.refine)
            for i in range(k):
                ins = [seg["hs"], feat] if i == 0 else [seg["rw"]]
                out[f"refine.{i}.0"] = ([seg["hs"] if i == k - 1 else seg["rw"]], ins)
        rest = self.head.weight.shape[1] - self._head_skip
        out["head"] = ([(self.head.weight.shape[0],) * 2], [seg["hs"], (rest, rest)])
        return out

    def _widen_state(self, state: dict[str, torch.Tensor]) -> tuple[dict, list[str]]:
        """``state`` of a narrower U-Net (same feature extractors and fusion) placed in this
        network's tensors: old weights at the old channels; weights from new input channels to
        old output channels zero, so the network computes what the narrow one did; the new
        output channels keep their random initialisation, so they carry signal that the zero
        weights learn from. Returns the state and the names widened ([] when none)."""
        own = self.state_dict()
        if "down1.0.weight" not in state or \
                state["down1.0.weight"].shape[0] == own["down1.0.weight"].shape[0]:
            return state, []
        old = {f"w{i}": state[f"down{i + 1}.0.weight"].shape[0] for i in range(_DOWNS)}
        old["hs"] = state["up4.0.weight"].shape[1]
        old["rw"] = state["refine.0.0.weight"].shape[0] if "refine.0.0.weight" in state \
            else old["hs"]

        layouts = self._unet_layouts(old)
        if any(o > n for outs, ins in layouts.values() for o, n in outs + ins):
            raise RuntimeError("Error(s) in loading state_dict: the weights' U-Net is wider "
                               "than this network's (a network can grow, not shrink)")

        def old_index(layout: list) -> torch.Tensor:
            idx, off = [], 0
            for o, n in layout:
                idx.append(torch.arange(off, off + o))
                off += n
            return torch.cat(idx)

        state, widened = dict(state), []
        for module, (outs, ins) in layouts.items():
            oi, ii = old_index(outs), old_index(ins)
            for name in [k for k in own if k.rsplit(".", 1)[0] == module]:
                if name not in state or state[name].shape == own[name].shape:
                    continue  # unchanged, or a scalar (BatchNorm's step count)
                src, dst = state[name], own[name].clone()
                if dst.ndim == 1:
                    dst[oi] = src.to(dst.dtype)
                else:
                    # ConvTranspose2d stores (in, out, k, k), Conv2d (out, in, k, k)
                    o_dim, i_dim = (1, 0) if module.startswith("up") else (0, 1)
                    new_in = torch.ones(dst.shape[i_dim], dtype=torch.bool)
                    new_in[ii] = False
                    rows = dst.index_select(o_dim, oi)
                    rows.index_fill_(i_dim, new_in.nonzero().flatten(), 0.0)
                    if src.shape[i_dim] != len(ii) or src.shape[o_dim] != len(oi):
                        raise RuntimeError(f"Error(s) in loading state_dict: size mismatch for "
                                           f"{name}: {tuple(src.shape)} does not fit "
                                           f"{tuple(dst.shape)} grown")
                    rows.index_copy_(i_dim, ii, src.to(dst.dtype))
                    dst.index_copy_(o_dim, oi, rows)
                state[name] = dst
                widened.append(name)
        return state, widened

    def load_grown(self, state: dict[str, torch.Tensor]) -> list[str]:
        """Load weights of the same network without the full-resolution refinement, without
        the timing inputs and/or with a narrower U-Net.

        Every tensor of ``state`` must fit, except that the refinement's tensors may be
        missing (they keep their identity initialisation); with ``timing``, the first
        convolutions of both feature extractors and the head may lack exactly the timing input
        channels (those weights start at zero); and the U-Net's widths (``widths``, the
        refinement's width) may be smaller (see :meth:`_widen_state`). Either way the network
        computes exactly what the weights computed before. Returns the names that were grown.

        Raises:
            RuntimeError: unexpected, mismatched or other missing tensors (as
                ``load_state_dict``).
        """
        state, widened = self._widen_state(dict(state))
        own = self.state_dict()
        timed: list[str] = []
        if self.timing:
            extra = dict(zip(self.TIMING_INPUTS, (self._timing_in[0], self._timing_in[1],
                                                  sum(self._timing_in))))
            for name, add in extra.items():
                old, new = state.get(name), own[name]
                if (old is not None and old.shape[1] + add == new.shape[1]
                        and old.shape[0] == new.shape[0] and old.shape[2:] == new.shape[2:]):
                    grown = torch.zeros_like(new)
                    grown[:, :old.shape[1]] = old.to(new.dtype)
                    state[name] = grown
                    timed.append(name)
            if timed and len(timed) != len(extra):
                raise RuntimeError(f"Error(s) in loading state_dict: only {timed} lack the "
                                   "timing inputs")
        missing, unexpected = self.load_state_dict(state, strict=False)
        other = [k for k in missing if not k.startswith(self.GROWN_PREFIXES)]
        grown_refine = {k for k in own if k.startswith(self.GROWN_PREFIXES)}
        if missing and not other and set(missing) != grown_refine:
            other = sorted(set(missing))  # part of a refinement: not a network to grow from
        if other or unexpected:
            raise RuntimeError(f"Error(s) in loading state_dict: missing {other[:3]}, "
                               f"unexpected {list(unexpected)[:3]}")
        if missing:
            self._init_refine()
        return list(missing) + timed + widened

    @property
    def needs_contrast(self) -> bool:
        """True when ``forward`` needs the sensor's contrast threshold (``prior="edi_c"``)."""
        return self.prior == "edi_c"

    def forward(self, blurry: torch.Tensor, voxels: torch.Tensor,
                contrast: torch.Tensor | float | None = None) -> torch.Tensor:
        """Residuals (B, 2N, C, H, W) from blurry (B, C, H, W) and voxels (B, 2N, H, W).

        ``contrast``: the threshold c (log intensity per event), a number or one per sample
        (B,); used only by networks that need it (:attr:`needs_contrast`), ignored otherwise.

        Raises:
            ShapeError: channel counts differ from the model's, or sizes disagree.
            InputError: the network needs ``contrast`` and got none or a non-positive one.
        """
        check_shape(blurry, ("B", self.channels, "H", "W"), "blurry")
        m = 2 * self.n
        check_shape(voxels, (blurry.shape[0], 2 * m if self.timing else m, blurry.shape[2],
                             blurry.shape[3]), "voxels")
        h, w = blurry.shape[-2:]
        mult = 2 ** _DOWNS
        pad = (0, (-w) % mult, 0, (-h) % mult)
        if any(pad):
            blurry = F.pad(blurry, pad, mode="replicate")
            voxels = F.pad(voxels, pad, mode="replicate")
        extra: list[torch.Tensor] = []  # timing inputs: after all the others
        if self.prior != "none":
            ladder: Any = self.prior_contrasts
            if self.needs_contrast:
                ladder = self._ladder(contrast, blurry)
            counts = voxels[:, :m]
            middle, residuals = edi_prior(blurry, counts, ladder)
            if self.timing:
                levels = voxels[:, m:]
                rung = ladder[:, 1:2] if torch.is_tensor(ladder) else ladder[1:2]
                lmid, lres = edi_prior(blurry, levels, rung)
                extra = [lmid.flatten(1, 2), levels, lres.flatten(1, 3)]
            blurry = torch.cat([blurry, middle.flatten(1, 2)], 1)
            voxels = torch.cat([counts, residuals.flatten(1, 3)], 1)

        b_in, e_in = blurry, voxels
        if extra:
            b_in, e_in = torch.cat([blurry, extra[0]], 1), torch.cat([voxels, *extra[1:]], 1)
        sb, se = self.ccb(self.blur_fe(b_in), self.event_fe(e_in))
        x0 = self.sfb(sb, se)
        x1 = self.down1(x0)
        x2 = self.down2(x1)
        x3 = self.down3(x2)
        x = self.res(self.down4(x3))
        x = self.up1(x)
        x = self.up2(torch.cat([x, x3], 1))
        x = self.up3(torch.cat([x, x2], 1))
        x = self.up4(torch.cat([x, x1], 1))
        if self.refine is not None:
            x = self.refine(torch.cat([x, x0], 1))
        out = self.head(torch.cat([x, blurry, voxels, *extra], 1))[..., :h, :w]
        return out.reshape(out.shape[0], 2 * self.n, self.channels, h, w)

    def _ladder(self, contrast: torch.Tensor | float | None, like: torch.Tensor) -> torch.Tensor:
        """(B, K) thresholds: the given c times the relative ladder."""
        if contrast is None:
            raise InputError("this network needs the contrast threshold c with every frame",
                             hint="pass contrast=… (the pipeline estimates it as EDI does)")
        c = torch.as_tensor(contrast, dtype=torch.float32, device=like.device).reshape(-1)
        if c.numel() == 1:
            c = c.expand(like.shape[0])
        if c.shape[0] != like.shape[0]:
            raise ShapeError(f"got {c.shape[0]} contrast thresholds for a batch of "
                             f"{like.shape[0]}")
        if not bool(torch.isfinite(c).all() and (c > 0).all()):
            raise InputError(f"contrast thresholds must be positive and finite, got "
                             f"{c.tolist()[:4]}")
        rel = torch.tensor(self.prior_contrasts, dtype=torch.float32, device=like.device)
        return c[:, None] * rel[None]

    def extra_repr(self) -> str:
        prior = f", prior={self.prior!r}" if self.prior != "none" else ""
        return f"variant={self.variant!r}{prior}"


# --------------------------------------------------------------------------------------------
# Named variants: arguments only; N and channels are chosen at creation (n=, channels=).
# Figures for gray, N = 3, 346×260 (count_macs). attn_norm: the paper's "none" for trmd_paper;
# the size-independent "spatial" elsewhere until training measures which one ships.

_variant_args: dict[str, dict[str, Any]] = {
    # the paper's width: 19.26 M parameters, 21.1 GMACs
    "trmd_paper": dict(feat_width=32, widths=(64, 128, 256, 512), num_res_blocks=2,
                       norm="batch", attn_norm="none"),
    # in between: three quarters of the paper's widths, 10.8 M parameters, 11.9 GMACs
    "trmd_base": dict(feat_width=24, widths=(48, 96, 192, 384), num_res_blocks=2,
                      norm="batch", attn_norm="spatial"),
    # 4.8 M parameters, 5.4 GMACs: sized for ≤ 0.15 s per frame on 2 CPU cores
    # (bench/bench_renet.py); full-resolution layers dominate its time, so they stay narrow
    "trmd_small": dict(feat_width=16, widths=(32, 64, 128, 256), num_res_blocks=2,
                       norm="batch", attn_norm="spatial"),
    # trmd_small given the EDI prior (models/prior.py): a departure from the paper
    "trmd_small_edi": dict(feat_width=16, widths=(32, 64, 128, 256), num_res_blocks=2,
                           norm="batch", attn_norm="spatial", prior="edi"),
    # trmd_small_edi with the ladder around a given threshold (estimated per frame in use)
    "trmd_small_edi_c": dict(feat_width=16, widths=(32, 64, 128, 256), num_res_blocks=2,
                             norm="batch", attn_norm="spatial", prior="edi_c"),
    # trmd_small_edi_c with three 3×3 convs (24 channels) at full resolution over [last
    # up-step, fused features] (refine): the paper's U-Net has no full-resolution skip
    "trmd_small_edi_c_fr": dict(feat_width=16, widths=(32, 64, 128, 256), num_res_blocks=2,
                                norm="batch", attn_norm="spatial", prior="edi_c", refine=3,
                                refine_width=24),
    # trmd_small_edi_c_fr given the voxels' sub-bin timing too (voxel.scer_levels)
    "trmd_small_edi_c_fr_t": dict(feat_width=16, widths=(32, 64, 128, 256), num_res_blocks=2,
                                  norm="batch", attn_norm="spatial", prior="edi_c", refine=3,
                                  refine_width=24, timing=True),
    # 13.5 k parameters: for tests only
    "test_trmd": dict(feat_width=4, widths=(4, 8, 8, 8), num_res_blocks=1,
                      norm="batch", attn_norm="spatial"),
}


def variant_args(name: str) -> dict[str, Any]:
    """The registered arguments of a variant (a copy)."""
    return dict(_variant_args[name])


def _create_renet(variant: str, **kwargs: Any) -> RENet:
    args = {**_variant_args[variant], **kwargs}
    model = RENet(**args)
    model.variant = variant
    return model


@register_model
def trmd_paper(**kwargs: Any) -> RENet:
    """RE-Net at the paper's width (≈ 19.3 M parameters)."""
    return _create_renet("trmd_paper", **kwargs)


@register_model
def trmd_base(**kwargs: Any) -> RENet:
    """RE-Net between the paper's width and ``trmd_small``."""
    return _create_renet("trmd_base", **kwargs)


@register_model
def trmd_small(**kwargs: Any) -> RENet:
    """RE-Net sized for CPU inference at DAVIS346 resolution."""
    return _create_renet("trmd_small", **kwargs)


@register_model
def trmd_small_edi(**kwargs: Any) -> RENet:
    """``trmd_small`` given EDI's frames for a ladder of contrasts as extra inputs."""
    return _create_renet("trmd_small_edi", **kwargs)


@register_model
def trmd_small_edi_c(**kwargs: Any) -> RENet:
    """``trmd_small_edi`` with the ladder scaled by a threshold given with every frame."""
    return _create_renet("trmd_small_edi_c", **kwargs)


@register_model
def trmd_small_edi_c_fr(**kwargs: Any) -> RENet:
    """``trmd_small_edi_c`` with a full-resolution refinement before the head."""
    return _create_renet("trmd_small_edi_c_fr", **kwargs)


@register_model
def trmd_small_edi_c_fr_t(**kwargs: Any) -> RENet:
    """``trmd_small_edi_c_fr`` that also sees when within a bin the events came."""
    return _create_renet("trmd_small_edi_c_fr_t", **kwargs)


@register_model
def test_trmd(**kwargs: Any) -> RENet:
    """Tiny RE-Net for tests."""
    return _create_renet("test_trmd", **kwargs)


# --------------------------------------------------------------------------------------------
# Profiling


def count_params(model: nn.Module) -> int:
    """Number of parameters (buffers such as BatchNorm statistics excluded)."""
    return sum(p.numel() for p in model.parameters())


def count_macs(model: RENet, h: int, w: int) -> int:
    """Multiply-accumulates of one forward pass on a (1, C, h, w) frame.

    Counted with forward hooks: Conv2d (output elements × C_in/groups × k²), ConvTranspose2d
    (input elements × C_out/groups × k², the multiplies actually done), Linear, and the two
    C×C×HW matmuls of each :class:`ChannelAttention`, and the single gate conv each
    :class:`SpatialFusionBlock` runs (its convs are not called as modules). Element-wise work
    (ReLU, softmax, norms, padding) is not counted. The count is for the padded size the
    network really runs at.
    """
    total = 0

    def conv_hook(mod: nn.Module, inp: tuple, out: torch.Tensor) -> None:
        nonlocal total
        k = math.prod(mod.kernel_size)
        if isinstance(mod, nn.ConvTranspose2d):
            total += inp[0].numel() * (mod.out_channels // mod.groups) * k
        else:
            total += out.numel() * (mod.in_channels // mod.groups) * k

    def linear_hook(mod: nn.Module, inp: tuple, out: torch.Tensor) -> None:
        nonlocal total
        total += out.numel() * mod.in_features

    def attn_hook(mod: nn.Module, inp: tuple, out: torch.Tensor) -> None:
        nonlocal total
        b, c, hh, ww = inp[0].shape
        total += 2 * b * c * c * hh * ww  # K·Qᵀ, then attention·V

    def sfb_hook(mod: nn.Module, inp: tuple, out: torch.Tensor) -> None:
        nonlocal total
        total += out.numel() * 2 * out.shape[1]  # the one gate conv it runs (2C → C)

    handles = []
    for mod in model.modules():
        if isinstance(mod, (nn.Conv2d, nn.ConvTranspose2d)):
            handles.append(mod.register_forward_hook(conv_hook))
        elif isinstance(mod, nn.Linear):
            handles.append(mod.register_forward_hook(linear_hook))
        elif isinstance(mod, ChannelAttention):
            handles.append(mod.register_forward_hook(attn_hook))
        elif isinstance(mod, SpatialFusionBlock):
            handles.append(mod.register_forward_hook(sfb_hook))
    p = next(model.parameters())
    was_training = model.training
    try:
        model.eval()
        with torch.no_grad():
            model(torch.zeros(1, model.channels, h, w, device=p.device, dtype=p.dtype),
                  torch.zeros(1, (4 if model.timing else 2) * model.n, h, w, device=p.device,
                              dtype=p.dtype),
                  0.25)  # a threshold, for networks that take one
    finally:
        for hd in handles:
            hd.remove()
        model.train(was_training)
    return total
