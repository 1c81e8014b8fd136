"""What RE-Net is given, and how its inputs reach the network.

:class:`RENetInputs` holds one batch: the blurry frame, the SCER voxels and — for the networks
that take them — the voxels' sub-bin timing and the sensor's contrast threshold.
:class:`RENetNeeds` says which of those optional inputs a network takes (``net.needs``).

An *input encoder* turns the inputs into what the two feature extractors and the head see. It
is chosen once, when the network is built (:func:`build_encoder`), so the network's ``forward``
has a single path:

===================================  ========================================================
:class:`PlainInputs`                 the paper's: B to the blur branch, V to the event branch
:class:`EdiPriorInputs`              and EDI's frames for a fixed contrast ladder
                                     (``prior="edi"``)
:class:`GivenContrastEdiPriorInputs` the same, the ladder around a threshold given with every
                                     frame (``prior="edi_c"``)
:class:`TimingInputs`                a prior encoder's, and the sub-bin timing with EDI
                                     computed from it (``timing=True``)
===================================  ========================================================

Encoders hold no weights: the EDI prior is physics (:func:`~trmd_cli.models.prior.edi_prior`),
so they add no state-dict entries.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import nn

from ..errors import InputError, ShapeError, check_shape
from .prior import edi_prior

__all__ = [
    "PRIORS",
    "RENetInputs",
    "RENetNeeds",
    "EncodedInputs",
    "InputEncoder",
    "PlainInputs",
    "EdiPriorInputs",
    "GivenContrastEdiPriorInputs",
    "TimingInputs",
    "build_encoder",
]

#: physical priors the network can be given besides B and V (see :mod:`trmd_cli.models.prior`)
PRIORS = ("none", "edi", "edi_c")


@dataclass(frozen=True)
class RENetNeeds:
    """What a network takes besides the blurry frame and the counts.

    Attributes:
        contrast: the sensor's contrast threshold c with every sample (:attr:`RENetInputs.
            contrast`).
        timing: the voxels' sub-bin timing (:attr:`RENetInputs.levels`).
    """

    contrast: bool = False
    timing: bool = False


@dataclass(frozen=True, eq=False)
class RENetInputs:
    """One batch of what RE-Net is given.

    Attributes:
        blurry: (B, C, H, W) blurry frames, intensity in [0, 1]; C is the network's ``channels``.
        counts: (B, 2N, H, W) SCER voxels (:func:`trmd_cli.voxel.scer_voxels`): signed event
            counts from the middle instant to each other instant k ≠ N, in time order.
        levels: (B, 2N, H, W) the same instants with the sub-bin timing kept
            (:func:`trmd_cli.voxel.scer_levels`), in events. Taken by networks with
            ``needs.timing``, ignored by the others. Without raw events the counts stand in.
        contrast: the contrast threshold c in log intensity per event: one number, or a (B,)
            tensor (one per sample). Taken by networks with ``needs.contrast``, ignored by the
            others.

    Example::

        >>> import torch
        >>> from trmd_cli.models import RENetInputs, create_model
        >>> net = create_model("test_trmd").eval()
        >>> net(RENetInputs(torch.rand(1, 1, 37, 53), torch.randn(1, 6, 37, 53))).shape
        torch.Size([1, 6, 1, 37, 53])
    """

    blurry: torch.Tensor
    counts: torch.Tensor
    levels: torch.Tensor | None = None
    contrast: torch.Tensor | float | None = None

    def check(self, n: int, channels: int, needs: RENetNeeds) -> None:
        """That the shapes fit a network for N = ``n`` and ``channels``, and that what it
        ``needs`` is there.

        Raises:
            ShapeError: channel counts differ from the network's, or sizes disagree.
            InputError: a needed input is missing, or a threshold is not positive and finite.
        """
        check_shape(self.blurry, ("B", channels, "H", "W"), "blurry")
        b, _, h, w = self.blurry.shape
        check_shape(self.counts, (b, 2 * n, h, w), "counts")
        if needs.timing:
            if self.levels is None:
                raise InputError("this network needs the voxels' sub-bin timing with every "
                                 "frame", hint="pass `levels` (trmd_cli.voxel.scer_levels; "
                                 "without raw events the counts stand in)")
            check_shape(self.levels, tuple(self.counts.shape), "levels")
        if needs.contrast:
            if self.contrast is None:
                raise InputError("this network needs the contrast threshold c with every frame",
                                 hint="pass `contrast` (the pipeline estimates it as EDI does)")
            c = torch.as_tensor(self.contrast, dtype=torch.float32).reshape(-1)
            if c.numel() != 1 and c.shape[0] != b:
                raise ShapeError(f"got {c.shape[0]} contrast thresholds for a batch of {b}")
            if not bool(torch.isfinite(c).all() and (c > 0).all()):
                raise InputError(f"contrast thresholds must be positive and finite, got "
                                 f"{c.tolist()[:4]}")

    def padded(self, multiple: int) -> RENetInputs:
        """The images replicate-padded on the right and bottom to a multiple of ``multiple``
        pixels: a frame already of that size is not shifted. The threshold is unchanged."""
        h, w = self.blurry.shape[-2:]
        pad = (0, (-w) % multiple, 0, (-h) % multiple)
        if not any(pad):
            return self
        levels = None if self.levels is None else F.pad(self.levels, pad, mode="replicate")
        return replace(self, blurry=F.pad(self.blurry, pad, mode="replicate"),
                       counts=F.pad(self.counts, pad, mode="replicate"), levels=levels)


@dataclass(frozen=True, eq=False)
class EncodedInputs:
    """What an input encoder hands the network, at the padded size.

    Attributes:
        blur: (B, blur_channels, H, W), the blur feature extractor's input.
        event: (B, event_channels, H, W), the event feature extractor's input.
        head: what the head sees after the decoder's features, joined in this order
            (blur_channels + event_channels channels in all).
    """

    blur: torch.Tensor
    event: torch.Tensor
    head: tuple[torch.Tensor, ...]


class InputEncoder(nn.Module):
    """Base of the input encoders: ``forward(RENetInputs) → EncodedInputs``, no weights.

    Attributes:
        needs: what the encoder takes besides B and the counts.
        blur_channels, event_channels: channels of :class:`EncodedInputs` ``blur`` and
            ``event``, for the N and colour channels it was built for.
        edi_at: where EDI's residuals at the ladder's second rung (2N·C channels) start among
            the head's inputs after the decoder features; None without the prior.
    """

    def __init__(self, n: int, channels: int) -> None:
        super().__init__()
        self.n, self.channels = n, channels
        self.needs = RENetNeeds()
        self.blur_channels, self.event_channels = channels, 2 * n
        self.edi_at: int | None = None

    def forward(self, x: RENetInputs) -> EncodedInputs:
        raise NotImplementedError


class PlainInputs(InputEncoder):
    """The paper's inputs: B to the blur branch, the counts V to the event branch; the head
    sees [B, V]."""

    def forward(self, x: RENetInputs) -> EncodedInputs:
        return EncodedInputs(x.blurry, x.counts, (x.blurry, x.counts))


class EdiPriorInputs(InputEncoder):
    """B and the counts with EDI's frames for a fixed ladder of contrasts (a departure from
    the paper): EDI's middle frames join B, its residuals join V (:func:`edi_prior`).

    Args:
        contrasts: the ladder, ≥ 2 positive thresholds in log intensity per event.
    """

    def __init__(self, n: int, channels: int, contrasts: Sequence[float]) -> None:
        super().__init__(n, channels)
        #: the contrast ladder (for :class:`GivenContrastEdiPriorInputs`, multiples of c)
        self.contrasts = tuple(float(c) for c in contrasts)
        k, m = len(self.contrasts), 2 * n
        self.blur_channels = channels * (1 + k)
        self.event_channels = m * (1 + k * channels)
        # head inputs: [B, middles (K·C), V (2N), residuals (K·2N·C)]
        self.edi_at = channels * (1 + k) + m + m * channels

    def ladder(self, x: RENetInputs) -> Sequence[float] | torch.Tensor:
        """The K thresholds, the same for every sample."""
        return self.contrasts

    def forward(self, x: RENetInputs) -> EncodedInputs:
        return self.encode(x, self.ladder(x))

    def encode(self, x: RENetInputs, ladder: Sequence[float] | torch.Tensor) -> EncodedInputs:
        """The inputs with EDI's frames for ``ladder`` (K thresholds, or (B, K))."""
        middle, residuals = edi_prior(x.blurry, x.counts, ladder)
        blur = torch.cat([x.blurry, middle.flatten(1, 2)], 1)
        event = torch.cat([x.counts, residuals.flatten(1, 3)], 1)
        return EncodedInputs(blur, event, (blur, event))

    def extra_repr(self) -> str:
        return f"contrasts={self.contrasts}"


class GivenContrastEdiPriorInputs(EdiPriorInputs):
    """:class:`EdiPriorInputs` with the ladder scaled by the threshold c given with every frame
    (``needs.contrast``); ``contrasts`` are multiples of c."""

    def __init__(self, n: int, channels: int, contrasts: Sequence[float]) -> None:
        super().__init__(n, channels, contrasts)
        self.needs = RENetNeeds(contrast=True)

    def ladder(self, x: RENetInputs) -> torch.Tensor:
        """(B, K) thresholds: each sample's c times the relative ladder."""
        like = x.blurry
        c = torch.as_tensor(x.contrast, dtype=torch.float32, device=like.device).reshape(-1)
        if c.numel() == 1:
            c = c.expand(like.shape[0])
        rel = torch.tensor(self.contrasts, dtype=torch.float32, device=like.device)
        return c[:, None] * rel[None]


class TimingInputs(InputEncoder):
    """A prior encoder's inputs and the voxels' sub-bin timing (``needs.timing``): EDI's
    middle frame computed from the levels at the ladder's second rung joins B's inputs; the
    levels and that EDI's residuals join V's. They come after the prior's everywhere, so the
    weights of a network without them are a slice of this one's (:mod:`.grow`).

    Args:
        prior: the encoder of B and the counts.
    """

    def __init__(self, prior: EdiPriorInputs) -> None:
        super().__init__(prior.n, prior.channels)
        self.prior = prior
        self.needs = replace(prior.needs, timing=True)
        m, c = 2 * prior.n, prior.channels
        self.blur_channels = prior.blur_channels + c
        self.event_channels = prior.event_channels + m * (1 + c)
        self.edi_at = prior.edi_at

    def forward(self, x: RENetInputs) -> EncodedInputs:
        assert x.levels is not None  # RENetInputs.check
        ladder = self.prior.ladder(x)
        enc = self.prior.encode(x, ladder)
        rung = ladder[:, 1:2] if torch.is_tensor(ladder) else ladder[1:2]
        middle, residuals = edi_prior(x.blurry, x.levels, rung)
        middle, residuals = middle.flatten(1, 2), residuals.flatten(1, 3)
        return EncodedInputs(torch.cat([enc.blur, middle], 1),
                             torch.cat([enc.event, x.levels, residuals], 1),
                             (*enc.head, middle, x.levels, residuals))


def build_encoder(n: int, channels: int, prior: str = "none",
                  contrasts: Sequence[float] = (), timing: bool = False) -> InputEncoder:
    """The input encoder of a RE-Net built with these arguments (see :class:`~.renet.RENet`).

    Raises:
        InputError: ``prior`` is unknown, or ``timing`` is asked for without a prior.
    """
    if prior not in PRIORS:
        raise InputError(f"prior {prior!r} is not one of {', '.join(PRIORS)}")
    if prior == "none":
        if timing:
            raise InputError("timing needs a prior (prior='edi' or 'edi_c')")
        return PlainInputs(n, channels)
    cls = GivenContrastEdiPriorInputs if prior == "edi_c" else EdiPriorInputs
    encoder = cls(n, channels, contrasts)
    return TimingInputs(encoder) if timing else encoder
