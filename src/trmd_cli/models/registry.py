"""Model registry in the timm manner: named variants are tiny factories over argument dicts.

A factory is registered with :func:`register_model` under its function name; :func:`create_model`
looks the name up and calls it with overrides. Variants are data (the argument table in
:mod:`trmd_cli.models.renet`), never switches inside a model.

Names retired from the registry stay usable as aliases (:func:`register_alias`): an old name
stands for a registered variant and the arguments that make it the network the old name built,
so recipes and weights files that use it keep working.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Callable
from typing import Any, TypeVar

from ..errors import InputError

__all__ = ["register_model", "register_alias", "resolve_model", "canonical_name",
           "create_model", "list_models", "list_aliases", "is_model", "model_entrypoint"]

F = TypeVar("F", bound=Callable[..., Any])

_model_entrypoints: dict[str, Callable[..., Any]] = {}
_aliases: dict[str, tuple[str, dict[str, Any]]] = {}


def register_model(fn: F) -> F:
    """Decorator: register ``fn`` as the factory of the variant named ``fn.__name__``."""
    name = fn.__name__
    if name in _model_entrypoints or name in _aliases:
        raise ValueError(f"model {name!r} is registered twice")
    _model_entrypoints[name] = fn
    return fn


def register_alias(old: str, name: str, **args: Any) -> None:
    """Let ``old`` stand for the registered variant ``name`` built with ``args``."""
    if old in _model_entrypoints or old in _aliases:
        raise ValueError(f"model {old!r} is registered twice")
    if name not in _model_entrypoints:
        raise ValueError(f"alias {old!r} names {name!r}, which is not registered")
    _aliases[old] = (name, dict(args))


def resolve_model(name: str) -> tuple[str, dict[str, Any]]:
    """(variant name, arguments over the variant's) that ``name`` stands for: ``(name, {})``
    for a registered variant (or an unknown name), the alias's target otherwise."""
    target, args = _aliases.get(name, (name, {}))
    return target, dict(args)


def canonical_name(name: str) -> str:
    """The registered variant an alias stands for; any other name as it is."""
    return resolve_model(name)[0]


def list_models(pattern: str | None = None) -> list[str]:
    """Registered variant names, sorted; ``pattern`` is a shell wildcard (``"trmd_*"``).
    Aliases are not listed (:func:`list_aliases`)."""
    names = sorted(_model_entrypoints)
    if pattern:
        names = [n for n in names if fnmatch.fnmatchcase(n, pattern)]
    return names


def list_aliases() -> dict[str, tuple[str, dict[str, Any]]]:
    """Old name → (variant, arguments over the variant's), for every alias."""
    return {old: (name, dict(args)) for old, (name, args) in sorted(_aliases.items())}


def is_model(name: str) -> bool:
    """True for a registered variant or an alias of one."""
    return name in _model_entrypoints or name in _aliases


def model_entrypoint(name: str) -> Callable[..., Any]:
    """The factory of the registered variant ``name``; :class:`InputError` naming the known
    variants otherwise."""
    try:
        return _model_entrypoints[name]
    except KeyError:
        raise InputError(f"unknown model {name!r}",
                         hint=f"choose one of {', '.join(list_models())}") from None


def create_model(name: str, **overrides: Any):
    """Build the variant ``name`` (or the one an alias stands for); ``overrides`` replace
    entries of its arguments.

    Example::

        >>> from trmd_cli.models import create_model
        >>> model = create_model("test_trmd", n=2, channels=3)
        >>> model.n, model.channels
        (2, 3)
    """
    target, args = resolve_model(name)
    return model_entrypoint(target)(**{**args, **overrides})
