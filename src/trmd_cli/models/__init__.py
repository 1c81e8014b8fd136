"""Learned models: RE-Net variants, their registry, and the inference wrapper.

Importing this package imports torch; the CLI does so only inside the commands that need it.

Example::

    >>> from trmd_cli.models import create_model, list_models
    >>> list_models("trmd_small_edi_c*")
    ['trmd_small_edi_c', 'trmd_small_edi_c_fr', 'trmd_small_edi_c_fr_t']
    >>> net = create_model("trmd_small", n=3, channels=1)
"""

from __future__ import annotations

from .registry import create_model, is_model, list_models, model_entrypoint, register_model
from .renet import (
    ATTN_NORMS,
    NORMS,
    RENet,
    channel_attention_logits,
    channel_cross_attention,
    count_macs,
    count_params,
    variant_args,
)

__all__ = [
    "ATTN_NORMS",
    "NORMS",
    "RENet",
    "channel_attention_logits",
    "channel_cross_attention",
    "count_macs",
    "count_params",
    "create_model",
    "is_model",
    "list_models",
    "model_entrypoint",
    "register_model",
    "variant_args",
]
