"""Old variant names: what weights files and recipes called the training stages that led to
the shipped network. Stages are not architectures, so they are not registered variants; each
old name stands for a registered variant and the arguments it was built with. Kept apart from
:mod:`~trmd_cli.models.renet` so that describing a weights file needs no torch.
"""

from __future__ import annotations

from typing import Any

__all__ = ["ALIASES", "current_name"]

#: names that weights files and recipes used for the training stages that led to the shipped
#: network (stages, not architectures): old name → (variant, its arguments over the variant's)
ALIASES: dict[str, tuple[str, dict[str, Any]]] = {
    "trmd_small_edi": ("trmd_small", dict(prior="edi")),
    "trmd_small_edi_c": ("trmd_small", dict(prior="edi_c")),
    "trmd_small_edi_c_fr": ("trmd_small", dict(prior="edi_c", refine=3, refine_width=24)),
    "trmd_small_edi_c_fr_t": ("trmd_small_prior", {}),
}


def current_name(name: str) -> str:
    """The registered variant an old name stands for; any other name as it is."""
    return ALIASES.get(name, (name, {}))[0]
