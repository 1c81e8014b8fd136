"""Which floating-point precision the network runs in: float32, or mixed precision where the
hardware computes it natively (float16 on CUDA, bfloat16 on CPUs with AMX or AVX512-BF16).

Mixed precision only changes the convolutions and matrix products (``torch.autocast``); the
physics (EDI prior, reconstruction, losses) stays in float32. On CPUs without native bfloat16
it would be emulated and slower than float32, so ``"auto"`` never picks it there.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .errors import InputError

if TYPE_CHECKING:
    import torch

__all__ = ["PRECISIONS", "autocast", "cpu_has_native_bf16", "precision_name",
           "resolve_precision"]

#: Accepted names: ``auto`` = mixed where native, else float32.
PRECISIONS = ("auto", "fp32", "bf16", "fp16")


def cpu_has_native_bf16() -> bool:
    """True when this CPU multiplies bfloat16 in hardware (Intel AMX or AVX512-BF16)."""
    import torch

    checks = ("_is_amx_tile_supported", "_is_avx512_bf16_supported")
    try:  # private torch helpers: absent on some builds, which then count as "no"
        return any(bool(getattr(torch.cpu, name)()) for name in checks
                   if hasattr(torch.cpu, name))
    except Exception:  # noqa: BLE001 — a probe must never stop the tool
        return False


def resolve_precision(precision: str, device: torch.device) -> torch.dtype | None:
    """The autocast dtype for ``precision`` on ``device``; None = plain float32.

    ``auto``: float16 on CUDA, bfloat16 on a CPU with native bfloat16, else float32.
    ``bf16`` / ``fp16`` force that dtype (``fp16`` only on CUDA: CPUs have no fast float16).

    Raises:
        InputError: unknown name, or fp16 asked for on a CPU.
    """
    import torch

    if precision not in PRECISIONS:
        raise InputError(f"unknown precision {precision!r}",
                         hint="use one of: " + ", ".join(PRECISIONS))
    if precision == "fp32":
        return None
    if precision == "auto":
        if device.type == "cuda":
            return torch.float16
        return torch.bfloat16 if device.type == "cpu" and cpu_has_native_bf16() else None
    if precision == "fp16" and device.type != "cuda":
        raise InputError("float16 needs a CUDA device",
                         hint="use `precision='bf16'` or `precision='fp32'`")
    return torch.bfloat16 if precision == "bf16" else torch.float16


def precision_name(dtype: torch.dtype | None) -> str:
    """``fp32`` for None (no autocast), else ``bf16`` / ``fp16``: what ran, for logs and meta."""
    import torch

    return {None: "fp32", torch.bfloat16: "bf16", torch.float16: "fp16"}[dtype]


def autocast(device: torch.device, dtype: torch.dtype | None):
    """``torch.autocast`` for ``dtype`` on ``device``, a no-op context when ``dtype`` is None."""
    import torch

    return torch.autocast(device_type=device.type, dtype=dtype or torch.float32,
                          enabled=dtype is not None)
