"""Training losses: a registry of small callables combined with weights from the recipe.

Every loss has the signature ``loss(outputs, batch, recipe) -> scalar tensor`` where

- ``outputs["residuals"]`` (B, 2N, C, H, W): what the network predicted;
- ``outputs["latent"]`` (B, 2N+1, C, H, W): the two-stage reconstruction from the blurry frame
  and those residuals (:func:`trmd_cli.reconstruct.reconstruct`), not clipped;
- ``batch["blurry"]`` (B, C, H, W) and ``batch["voxels"]`` (B, 2N, H, W) always exist;
  ``batch["sharp"]`` (B, 2N+1, C, H, W) and ``batch["contrast"]`` (B,) only for data with
  ground truth (``contrast`` may hold NaN for "unknown").

Only the *supervised* losses read ``batch["sharp"]``; the loop never does, so a recipe whose
weights name only unsupervised losses (``blur_consistency``, ``event_consistency``) trains on a
user's own recording without ground truth. Add a loss with :func:`register_loss`.

The paper's objective (Chen & Yu 2024) is ``residual + λ·middle`` with MSE and λ = 1.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from ..errors import InputError

__all__ = ["LOSSES", "register_loss", "total_loss", "penalty", "full_voxels",
           "LossFn", "SUPERVISED"]

LossFn = Callable[[dict, dict, object], torch.Tensor]

#: name → loss callable; the recipe's ``[loss]`` table gives each a weight
LOSSES: dict[str, LossFn] = {}
#: losses that need ``batch["sharp"]``
SUPERVISED: set[str] = set()

# Rec. 601 luma: the events of an RGB scene are taken to come from its luminance
_LUMA = (0.299, 0.587, 0.114)


def register_loss(name: str, *, supervised: bool = False) -> Callable[[LossFn], LossFn]:
    """Decorator adding a loss to :data:`LOSSES` under ``name``."""

    def deco(fn: LossFn) -> LossFn:
        LOSSES[name] = fn
        if supervised:
            SUPERVISED.add(name)
        return fn

    return deco


def penalty(diff: torch.Tensor, recipe) -> torch.Tensor:
    """Mean of ρ(diff) with ρ from ``recipe.loss.penalty``: mse (d²), l1 (|d|) or
    charbonnier (√(d² + ε²) − ε, zero at zero)."""
    kind = recipe.loss.penalty
    if kind == "mse":
        return diff.square().mean()
    if kind == "l1":
        return diff.abs().mean()
    if kind == "charbonnier":
        eps = recipe.loss.charbonnier_eps
        return (diff.square() + eps * eps).sqrt().mean() - eps
    raise InputError(f"unknown loss.penalty {kind!r}", hint="use mse, l1 or charbonnier")


def _sharp(batch: dict, name: str) -> torch.Tensor:
    sharp = batch.get("sharp")
    if sharp is None:
        raise InputError(f"loss '{name}' needs ground-truth sharp frames and this data has none",
                         hint=f"set loss.{name} = 0 and train with blur_consistency / "
                         "event_consistency")
    return sharp


@register_loss("residual", supervised=True)
def residual_loss(outputs: dict, batch: dict, recipe) -> torch.Tensor:
    """Predicted residuals vs the true ones (from the sharp frames): the paper's main term."""
    from ..reconstruct import residuals_from_latent

    target = residuals_from_latent(_sharp(batch, "residual"))
    return penalty(outputs["residuals"] - target, recipe)


@register_loss("middle", supervised=True)
def middle_loss(outputs: dict, batch: dict, recipe) -> torch.Tensor:
    """Reconstructed middle frame (index N) vs the sharp middle frame: the paper's λ term."""
    sharp = _sharp(batch, "middle")
    mid = sharp.shape[1] // 2
    return penalty(outputs["latent"][:, mid] - sharp[:, mid], recipe)


@register_loss("sequence", supervised=True)
def sequence_loss(outputs: dict, batch: dict, recipe) -> torch.Tensor:
    """All 2N+1 reconstructed frames vs the sharp sequence."""
    return penalty(outputs["latent"] - _sharp(batch, "sequence"), recipe)


@register_loss("blur_consistency")
def blur_consistency_loss(outputs: dict, batch: dict, recipe) -> torch.Tensor:
    """Mean of the 2N+1 frames, clipped to [0, 1], vs the blurry frame. Needs no sharp frames.

    The two-stage reconstruction makes the *unclipped* frames average to the blurry frame
    exactly, so this term is zero unless clipping bites (predicted frames leaving [0, 1]) or
    the outputs come from a head that is not constrained that way. It is there for fine-tuning
    without ground truth, where it keeps the frames physically possible.
    """
    mean = outputs["latent"].clamp(0.0, 1.0).mean(1)
    return penalty(mean - batch["blurry"], recipe)


def full_voxels(voxels: torch.Tensor) -> torch.Tensor:
    """SCER voxels (B, 2N, H, W) → (B, 2N+1, H, W) with the identically-zero V(N) inserted."""
    n = voxels.shape[1] // 2
    zero = torch.zeros_like(voxels[:, :1])
    return torch.cat([voxels[:, :n], zero, voxels[:, n:]], 1)


@register_loss("event_consistency")
def event_consistency_loss(outputs: dict, batch: dict, recipe) -> torch.Tensor:
    """Log-brightness change between consecutive frames vs c × the events between them.

    With b_j the signed event count between instants j and j+1 (differences of the SCER
    voxels), the event model says log(L_{j+1} + ε) − log(L_j + ε) ≈ c·b_j. c comes from
    ``batch["contrast"]`` where finite, else ``recipe.loss.contrast``; ε is
    ``recipe.loss.log_eps``. RGB frames are compared through their luma. Needs no sharp frames;
    noisy events and a wrong c make it a soft constraint, so a robust penalty suits it.
    """
    latent = outputs["latent"]
    if latent.shape[2] == 3:
        w = latent.new_tensor(_LUMA).view(1, 1, 3, 1, 1)
        gray = (latent * w).sum(2)
    else:
        gray = latent.mean(2)
    logl = torch.log(gray.clamp_min(0.0) + recipe.loss.log_eps)
    counts = full_voxels(batch["voxels"]).to(logl.dtype)
    b = counts[:, 1:] - counts[:, :-1]
    c = torch.full((latent.shape[0],), recipe.loss.contrast, dtype=logl.dtype,
                   device=logl.device)
    given = batch.get("contrast")
    if given is not None:
        given = given.to(device=logl.device, dtype=logl.dtype).reshape(-1)
        c = torch.where(torch.isfinite(given), given, c)
    return penalty(logl[:, 1:] - logl[:, :-1] - c.view(-1, 1, 1, 1) * b, recipe)


def total_loss(outputs: dict, batch: dict, recipe) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Σ weight × loss over the recipe's positive weights; also each term (detached)."""
    total = None
    parts: dict[str, torch.Tensor] = {}
    for name, weight in recipe.loss.weights.items():
        if weight <= 0:
            continue
        fn = LOSSES.get(name)
        if fn is None:
            raise InputError(f"unknown loss '{name}'", hint=f"known: {', '.join(sorted(LOSSES))}")
        value = fn(outputs, batch, recipe)
        parts[name] = value.detach()
        total = weight * value if total is None else total + weight * value
    if total is None:
        raise InputError("no loss has a positive weight",
                         hint="set e.g. [loss] residual = 1.0, middle = 1.0")
    return total, parts
