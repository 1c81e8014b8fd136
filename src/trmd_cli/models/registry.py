"""Model registry in the timm manner: named variants are tiny factories over argument dicts.

A factory is registered with :func:`register_model` under its function name; :func:`create_model`
looks the name up and calls it with overrides. Variants are data (the argument table in
:mod:`trmd_cli.models.renet`), never switches inside a model.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Callable
from typing import Any, TypeVar

from ..errors import InputError

__all__ = ["register_model", "create_model", "list_models", "is_model", "model_entrypoint"]

F = TypeVar("F", bound=Callable[..., Any])

_model_entrypoints: dict[str, Callable[..., Any]] = {}


def register_model(fn: F) -> F:
    """Decorator: register ``fn`` as the factory of the variant named ``fn.__name__``."""
    name = fn.__name__
    if name in _model_entrypoints:
        raise ValueError(f"model {name!r} is registered twice")
    _model_entrypoints[name] = fn
    return fn


def list_models(pattern: str | None = None) -> list[str]:
    """Registered variant names, sorted; ``pattern`` is a shell wildcard (``"trmd_*"``)."""
    names = sorted(_model_entrypoints)
    if pattern:
        names = [n for n in names if fnmatch.fnmatchcase(n, pattern)]
    return names


def is_model(name: str) -> bool:
    return name in _model_entrypoints


def model_entrypoint(name: str) -> Callable[..., Any]:
    """The factory of ``name``; :class:`InputError` naming the known variants otherwise."""
    try:
        return _model_entrypoints[name]
    except KeyError:
        raise InputError(f"unknown model {name!r}",
                         hint=f"choose one of {', '.join(list_models())}") from None


def create_model(name: str, **overrides: Any):
    """Build the registered variant ``name``; ``overrides`` replace entries of its arguments.

    Example::

        >>> from trmd_cli.models import create_model
        >>> model = create_model("test_trmd", n=2, channels=3)
        >>> model.n, model.channels
        (2, 3)
    """
    return model_entrypoint(name)(**overrides)
