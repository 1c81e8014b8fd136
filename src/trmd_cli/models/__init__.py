"""Learned models: RE-Net variants, their registry, weights files, and the inference wrapper.

Modules: :mod:`.renet` (the network and its named variants), :mod:`.blocks` (its layers),
:mod:`.inputs` (what it is given, and the input encoders), :mod:`.prior` (the EDI prior),
:mod:`.grow` (loading the weights of a smaller network), :mod:`.weights` (safetensors files),
:mod:`.estimator` (numpy in, latent frames out), :mod:`.registry`.

Names are imported on first use: :mod:`.weights` reads metadata without torch, and the CLI
imports torch only inside the commands that need it.

Example::

    >>> from trmd_cli.models import create_model, list_models
    >>> list_models("trmd_small*")
    ['trmd_small', 'trmd_small_prior']
    >>> net = create_model("trmd_small", n=3, channels=1)
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .inputs import RENetInputs, RENetNeeds
    from .registry import (
        canonical_name,
        create_model,
        is_model,
        list_aliases,
        list_models,
        model_entrypoint,
        register_model,
    )
    from .renet import (
        ALIASES,
        ATTN_NORMS,
        NORMS,
        RENet,
        channel_attention_logits,
        channel_cross_attention,
        count_macs,
        count_params,
        variant_args,
    )

_EXPORTS = {
    **dict.fromkeys(("RENetInputs", "RENetNeeds"), ".inputs"),
    **dict.fromkeys(("canonical_name", "create_model", "is_model", "list_aliases", "list_models",
                     "model_entrypoint", "register_model"), ".registry"),
    **dict.fromkeys(("ALIASES", "ATTN_NORMS", "NORMS", "RENet", "channel_attention_logits",
                     "channel_cross_attention", "count_macs", "count_params", "variant_args"),
                    ".renet"),
}

__all__ = [
    "ALIASES",
    "ATTN_NORMS",
    "NORMS",
    "RENet",
    "RENetInputs",
    "RENetNeeds",
    "canonical_name",
    "channel_attention_logits",
    "channel_cross_attention",
    "count_macs",
    "count_params",
    "create_model",
    "is_model",
    "list_aliases",
    "list_models",
    "model_entrypoint",
    "register_model",
    "variant_args",
]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    # the variants register themselves as renet is imported: before that the registry is empty
    importlib.import_module(".renet", __name__)
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_EXPORTS})
