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

What reaches the feature extractors and the head is an input encoder's choice, made when the
network is built (:mod:`trmd_cli.models.inputs`): the paper's B and V, or those with EDI's
frames (``prior``) and the voxels' sub-bin timing (``timing``), departures that give the network
the physics from the first step. ``refine`` (a departure, off in the paper's variant) adds 3×3
convs at full resolution between the last up-step and the head, over [decoder features, fused
features]: the paper's U-Net has no skip at full resolution, so every per-pixel detail passes
through the stride-2 encoder; on simulated data most of the remaining error is in that fine
detail. Weights of a network without these parts grow into one with them
(:mod:`trmd_cli.models.grow`).

Departures from the official code, deliberate: the SFB softmax runs over the two modalities
(as the paper writes) rather than over the 2C concatenated channels; each CCB branch has its own
output projection (the official code reuses the blur one); no dropout in the query/key
projections. ``attn_norm`` adds size-independent attention (see
:func:`~trmd_cli.models.blocks.channel_attention_logits`).

Any H×W is accepted: inputs are replicate-padded to a multiple of 16 and the output cropped back.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from ..errors import InputError
from .aliases import ALIASES
from .blocks import (
    ATTN_NORMS,
    NORMS,
    ChannelAttention,
    CrossChannelBlock,
    FeatureExtractor,
    NoRefinement,
    PointwiseConv,
    Refinement,
    ResBlock,
    SpatialFusionBlock,
    channel_attention_logits,
    channel_cross_attention,
    conv_act,
    up_act,
)
from .inputs import PRIORS, RENetInputs, RENetNeeds, build_encoder
from .prior import DEFAULT_CONTRASTS, RELATIVE_CONTRASTS
from .registry import register_alias, register_model, resolve_model

__all__ = [
    "RENet",
    "RENetInputs",
    "RENetNeeds",
    "ATTN_NORMS",
    "NORMS",
    "PRIORS",
    "ALIASES",
    "channel_attention_logits",
    "channel_cross_attention",
    "count_macs",
    "count_params",
    "variant_args",
    "trmd_paper",
    "trmd_base",
    "trmd_small",
    "trmd_small_prior",
    "test_trmd",
]

#: number of stride-2 stages; inputs are padded to a multiple of 2**_DOWNS
_DOWNS = 4


class RENet(nn.Module):
    """Residual-estimation network: :class:`~.inputs.RENetInputs` → residuals R(k) = L(k) − L(N).

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
            begins at EDI's quality and learns the correction. ``"edi_c"``: the same, with the
            ladder scaled by the contrast threshold given with every frame
            (``needs.contrast``).
        prior_contrasts: the contrast ladder of the prior (log intensity per event); for
            ``"edi_c"``, multiples of the given threshold.
        refine: number of 3×3 conv + ReLU layers at full resolution before the head (paper: 0).
            The first sees the last up-step's output and the fused features; they start as an
            identity on the up-step's output.
        refine_width: channels inside the refinement (default and minimum: the last
            up-step's, ``widths[0] // 2``); its last layer returns to that width for the head.
        timing: the network also takes the voxels' sub-bin timing (:func:`~trmd_cli.voxel.
            scer_levels`, ``needs.timing``) and EDI computed from it at the ladder's second
            rung. Needs a prior.

    Attributes:
        needs: what ``forward`` takes besides B and the counts (:class:`~.inputs.RENetNeeds`).
        args: every constructor argument, JSON-friendly: what weights metadata records.
        variant: the registered variant name (None when built directly).

    Shapes:
        blurry (B, C, H, W), counts and levels (B, 2N, H, W) → residuals (B, 2N, C, H, W),
        any H, W ≥ 1.

    Example::

        >>> from trmd_cli.models import RENetInputs, create_model
        >>> import torch
        >>> net = create_model("test_trmd").eval()
        >>> net(RENetInputs(torch.rand(1, 1, 37, 53), torch.randn(1, 6, 37, 53))).shape
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
        self.args: dict[str, Any] = dict(n=n, channels=channels, feat_width=feat_width,
                                         widths=list(widths), num_res_blocks=num_res_blocks,
                                         norm=norm, attn_norm=attn_norm)
        # each part is recorded only when present, so the metadata of weights written before
        # it existed stays what this writes for the same network
        if prior != "none":
            self.args.update(prior=prior, prior_contrasts=list(contrasts))
        if refine:
            self.args.update(refine=refine, refine_width=rw)
        if timing:
            self.args.update(timing=True)
        self.variant: str | None = None
        self.n, self.channels = n, channels
        m = 2 * n
        w0, w1, w2, w3 = widths

        self.encoder = build_encoder(n, channels, prior, contrasts, bool(timing))
        self.needs: RENetNeeds = self.encoder.needs
        blur_in, event_in = self.encoder.blur_channels, self.encoder.event_channels
        self.blur_fe = FeatureExtractor(blur_in, feat_width)
        self.event_fe = FeatureExtractor(event_in, feat_width)
        self.ccb = CrossChannelBlock(feat_width, norm, attn_norm)
        self.sfb = SpatialFusionBlock(feat_width)

        self.down1 = conv_act(feat_width, w0, 5, 2)
        self.down2 = conv_act(w0, w1, 5, 2)
        self.down3 = conv_act(w1, w2, 5, 2)
        self.down4 = conv_act(w2, w3, 5, 2)
        self.res = nn.Sequential(*[ResBlock(w3, norm) for _ in range(num_res_blocks)])
        self.up1 = up_act(w3, w2)
        self.up2 = up_act(2 * w2, w1)
        self.up3 = up_act(2 * w1, w0)
        self.up4 = up_act(2 * w0, hs)
        #: channels of the last up-step's output: the decoder features the head sees
        self.up_width = hs
        self.refine: Refinement | NoRefinement = (Refinement(hs, feat_width, refine, rw)
                                                  if refine else NoRefinement())
        self.head = PointwiseConv(hs + blur_in + event_in, m * channels)
        self.init_weights()

    def init_weights(self) -> None:
        """PyTorch defaults, except a near-zero head: training starts from R ≈ 0, i.e. every
        latent frame ≈ B, instead of random residuals — or, with the EDI prior, from EDI's
        residuals at the second contrast of the ladder (an identity from those inputs)."""
        if self.head.weight.is_meta:
            # shapes only (a weights file checked before it is built): no values to set, and
            # torch's first normal_ on the meta device costs seconds of lazy set-up
            return
        nn.init.normal_(self.head.weight, std=1e-3)
        nn.init.zeros_(self.head.bias)
        if isinstance(self.refine, Refinement):
            self.refine.init_identity()
        if self.encoder.edi_at is not None:
            first = self.up_width + self.encoder.edi_at
            with torch.no_grad():
                for j in range(2 * self.n * self.channels):
                    self.head.weight[j, first + j] += 1.0

    def forward(self, inputs: RENetInputs) -> torch.Tensor:
        """Residuals (B, 2N, C, H, W) of ``inputs`` (:class:`~.inputs.RENetInputs`).

        Raises:
            ShapeError: channel counts differ from the network's, or sizes disagree.
            InputError: the network needs an input (:attr:`needs`) that is missing or invalid.
        """
        inputs.check(self.n, self.channels, self.needs)
        h, w = inputs.blurry.shape[-2:]
        x = self.encoder(inputs.padded(2 ** _DOWNS))
        sb, se = self.ccb(self.blur_fe(x.blur), self.event_fe(x.event))
        x0 = self.sfb(sb, se)
        x1 = self.down1(x0)
        x2 = self.down2(x1)
        x3 = self.down3(x2)
        y = self.res(self.down4(x3))
        y = self.up1(y)
        y = self.up2(torch.cat([y, x3], 1))
        y = self.up3(torch.cat([y, x2], 1))
        y = self.refine(self.up4(torch.cat([y, x1], 1)), x0)
        out = self.head(torch.cat([y, *x.head], 1))[..., :h, :w]
        return out.reshape(out.shape[0], 2 * self.n, self.channels, h, w)

    def extra_repr(self) -> str:
        return f"variant={self.variant!r}"


# --------------------------------------------------------------------------------------------
# Named variants: arguments only; N and channels are chosen at creation (n=, channels=).
# Figures for gray, N = 3, 346×260 (count_macs). attn_norm: the paper's "none" for trmd_paper;
# the size-independent "spatial" elsewhere.

_SMALL = dict(feat_width=16, widths=(32, 64, 128, 256), num_res_blocks=2, norm="batch",
              attn_norm="spatial")

_variant_args: dict[str, dict[str, Any]] = {
    # the paper's width: 19.26 M parameters, 21.1 GMACs
    "trmd_paper": dict(feat_width=32, widths=(64, 128, 256, 512), num_res_blocks=2,
                       norm="batch", attn_norm="none"),
    # in between: three quarters of the paper's widths, 10.8 M parameters, 11.9 GMACs
    "trmd_base": dict(feat_width=24, widths=(48, 96, 192, 384), num_res_blocks=2,
                      norm="batch", attn_norm="spatial"),
    # 4.8 M parameters, 5.4 GMACs: sized for ≤ 0.15 s per frame on 2 CPU cores
    # (bench/bench_renet.py); full-resolution layers dominate its time, so they stay narrow
    "trmd_small": dict(_SMALL),
    # the shipped network, 4.84 M parameters, 7.65 GMACs: trmd_small given EDI's frames for
    # the ladder around the frame's threshold, from the counts and from the sub-bin timing,
    # and three 3×3 convs (24 channels) at full resolution over [last up-step, fused features]
    "trmd_small_prior": dict(_SMALL, prior="edi_c", refine=3, refine_width=24, timing=True),
    # 13.5 k parameters: for tests only
    "test_trmd": dict(feat_width=4, widths=(4, 8, 8, 8), num_res_blocks=1,
                      norm="batch", attn_norm="spatial"),
}



def variant_args(name: str) -> dict[str, Any]:
    """The arguments a variant, or an old name of one (:data:`ALIASES`), is built with (a
    copy). Raises KeyError for an unknown name."""
    target, extra = resolve_model(name)
    return {**_variant_args[target], **extra}


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
def trmd_small_prior(**kwargs: Any) -> RENet:
    """``trmd_small`` given EDI's frames around the frame's threshold, from the counts and the
    sub-bin timing, with a full-resolution refinement: the shipped network."""
    return _create_renet("trmd_small_prior", **kwargs)


@register_model
def test_trmd(**kwargs: Any) -> RENet:
    """Tiny RE-Net for tests."""
    return _create_renet("test_trmd", **kwargs)


for _old, (_new, _extra) in ALIASES.items():
    register_alias(_old, _new, **_extra)
del _old, _new, _extra


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
            zeros = torch.zeros(1, 2 * model.n, h, w, device=p.device, dtype=p.dtype)
        # every optional input: networks ignore what they do not take
        model(RENetInputs(torch.zeros(1, model.channels, h, w, device=p.device, dtype=p.dtype),
                          zeros, levels=zeros, contrast=0.25))
    finally:
        for hd in handles:
            hd.remove()
        model.train(was_training)
    return total
