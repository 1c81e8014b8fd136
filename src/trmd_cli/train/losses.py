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
user's own recording without ground truth (``trmd finetune``, which adds ``reblur`` and ``warp``:
the events' motion against the frames). Add a loss with :func:`register_loss`.

The paper's objective (Chen & Yu 2024) is ``residual + λ·middle`` with MSE and λ = 1.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from ..errors import InputError

__all__ = ["LOSSES", "LUMA", "register_loss", "total_loss", "penalty", "full_voxels",
           "LossFn", "SUPERVISED"]

LossFn = Callable[[dict, dict, object], torch.Tensor]

#: name → loss callable; the recipe's ``[loss]`` table gives each a weight
LOSSES: dict[str, LossFn] = {}
#: losses that need ``batch["sharp"]``
SUPERVISED: set[str] = set()

#: Rec. 601 luma: the events of an RGB scene are taken to come from its luminance
LUMA = (0.299, 0.587, 0.114)


def register_loss(name: str, *, supervised: bool = False) -> Callable[[LossFn], LossFn]:
    """Decorator adding a loss to :data:`LOSSES` under ``name``."""

    def deco(fn: LossFn) -> LossFn:
        LOSSES[name] = fn
        if supervised:
            SUPERVISED.add(name)
        return fn

    return deco


def _rho(diff: torch.Tensor, recipe) -> torch.Tensor:
    """ρ(diff) per element, ρ from ``recipe.loss.penalty``: mse (d²), l1 (|d|) or charbonnier
    (√(d² + ε²) − ε, zero at zero)."""
    kind = recipe.loss.penalty
    if kind == "mse":
        return diff.square()
    if kind == "l1":
        return diff.abs()
    if kind == "charbonnier":
        eps = recipe.loss.charbonnier_eps
        return (diff.square() + eps * eps).sqrt() - eps
    raise InputError(f"unknown loss.penalty {kind!r}", hint="use mse, l1 or charbonnier")


def penalty(diff: torch.Tensor, recipe) -> torch.Tensor:
    """Mean of ρ(diff) with ρ from ``recipe.loss.penalty`` (see :func:`_rho`)."""
    return _rho(diff, recipe).mean()


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
        w = latent.new_tensor(LUMA).view(1, 1, 3, 1, 1)
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


def _masked(diff: torch.Tensor, mask: torch.Tensor, recipe) -> torch.Tensor:
    """Mean of ρ(diff) (the recipe's penalty) over the pixels where ``mask`` (broadcast to
    ``diff``) is 1; 0 when no pixel is."""
    rho = _rho(diff, recipe)
    mask = mask.to(rho.dtype).expand_as(rho)
    return (rho * mask).sum() / mask.sum().clamp_min(1.0)


def _sample(frames: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """``frames`` (B, C, h, w) sampled at ``grid`` (B, K, h, w, 2; ``grid_sample``'s
    normalised coordinates, corners aligned): (B, K, C, h, w)."""
    import torch.nn.functional as F

    b, k = grid.shape[:2]
    c, h, w = frames.shape[1:]
    inp = frames.unsqueeze(1).expand(b, k, c, h, w).reshape(b * k, c, h, w)
    out = F.grid_sample(inp, grid.reshape(b * k, *grid.shape[2:]).to(inp.dtype),
                        mode="bilinear", padding_mode="border", align_corners=True)
    return out.reshape(b, k, c, *out.shape[-2:])


def _motion(batch: dict, name: str) -> None:
    if f"{name}_grid" not in batch:
        raise InputError(f"loss '{name}' needs the exposure's motion and this data has none",
                         hint=f"set loss.{name} = 0 (`trmd finetune` gives it the events' "
                         "motion)")


@register_loss("reblur")
def reblur_loss(outputs: dict, batch: dict, recipe) -> torch.Tensor:
    """The middle frame moved along the exposure's motion and averaged vs the blurry frame.

    ``batch["reblur_grid"]`` (B, J, h, w, 2) says where each pixel of the blurry frame was in
    the middle frame at J instants of the exposure (from the events' motion, e.g.
    :func:`trmd_cli.motion.estimate_motion`); ``batch["reblur_mask"]`` (B, 1, h, w) is 1 where
    every instant stays inside the frame and the motion is trusted. Unlike
    ``blur_consistency`` this is not satisfied by construction: only a sharp middle frame,
    blurred by the true motion, gives the blurry frame back. Needs no sharp frames.
    """
    _motion(batch, "reblur")
    mid = outputs["latent"][:, outputs["latent"].shape[1] // 2]
    reblurred = _sample(mid, batch["reblur_grid"]).mean(1)
    return _masked(reblurred - batch["blurry"], batch["reblur_mask"], recipe)


@register_loss("warp")
def warp_loss(outputs: dict, batch: dict, recipe) -> torch.Tensor:
    """Each latent frame L(k) vs the middle frame carried to instant k by the motion.

    ``batch["warp_grid"]`` (B, 2N+1, h, w, 2): where each pixel at instant k was in the middle
    frame; ``batch["warp_mask"]`` (B, 2N+1, 1, h, w): 1 where that point lies inside the frame
    and the motion is trusted. Needs no sharp frames.
    """
    _motion(batch, "warp")
    latent = outputs["latent"]
    mid = latent[:, latent.shape[1] // 2]
    carried = _sample(mid, batch["warp_grid"])
    return _masked(latent - carried, batch["warp_mask"], recipe)


@register_loss("deconv")
def deconv_loss(outputs: dict, batch: dict, recipe) -> torch.Tensor:
    """The 2N+1 frames vs the motion-aware deconvolution of the blurry frame along the events'
    motion (:func:`trmd_cli.deconv.motion_deblur`), where its guard trusts it.

    That deconvolution is the minimiser of the re-blur residual under a Huber gradient prior,
    solved once per window: this term carries the re-blur constraint with the prior the
    network's own gradient cannot give. ``batch["deconv"]`` (B, 2N+1, C, h, w) the frames,
    ``batch["deconv_mask"]`` (B, 2N+1, 1, h, w) the deconvolution's share of each (0 where the
    guard fell back to EDI). Needs no sharp frames.
    """
    if "deconv" not in batch:
        raise InputError("loss 'deconv' needs the motion-aware deconvolution and this data has "
                         "none", hint="set loss.deconv = 0 (`trmd finetune` computes it)")
    return _masked(outputs["latent"] - batch["deconv"], batch["deconv_mask"], recipe)


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
