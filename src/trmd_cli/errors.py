"""One family of typed errors.

Every error the library raises on bad input derives from :class:`TrmdError`; its message names
what is wrong, where (file, key, line), and how to fix it. The CLI turns these into one line on
stderr and exit code 2 — see :mod:`trmd_cli.cli.boundary`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

__all__ = [
    "TrmdError",
    "InputError",
    "FormatError",
    "ShapeError",
    "WeightsError",
    "OutputExistsError",
    "WriteError",
    "check_shape",
]


class TrmdError(Exception):
    """Base class: a problem the user can fix. ``exit_code`` is what the CLI returns."""

    exit_code = 2

    def __init__(self, message: str, *, path: str | Path | None = None, hint: str | None = None):
        self.path = None if path is None else str(path)
        self.hint = hint
        self.detail = message
        parts = [f"{self.path}: {message}" if self.path else message]
        if hint:
            parts.append(hint)
        super().__init__(" — ".join(parts))


class InputError(TrmdError):
    """Input values are wrong: NaN times, coordinates outside the sensor, bad options."""


class FormatError(TrmdError):
    """A file cannot be read: unknown format, truncated, corrupt, missing keys, pickled."""


class ShapeError(TrmdError, ValueError):
    """An array has the wrong shape (names expected and actual)."""


class WeightsError(TrmdError):
    """Weights file missing, corrupt, or for another architecture / N / channel count."""


class OutputExistsError(TrmdError):
    """The output path exists and is not empty; pass ``overwrite=True`` to replace it."""


class WriteError(TrmdError):
    """An output cannot be written where it was asked for: the disk is full, a quota or a file
    size limit is reached, the folder is read-only or not the user's. Nothing of the output is
    left behind (a previous output is untouched)."""


def check_shape(array, expected: Sequence[int | str | None], name: str = "array") -> None:
    """Raise :class:`ShapeError` unless ``array.shape`` matches ``expected``.

    ``expected`` holds ints (exact), strings (symbols that must agree with each other within
    the call, e.g. ``("B", "C", "H", "W")``) or ``None`` (anything). A leading ``"*"`` allows any
    number of leading dimensions.
    """
    shape = tuple(array.shape)
    exp = list(expected)
    if exp and exp[0] == "*":
        exp = exp[1:]
        if len(shape) < len(exp):
            raise ShapeError(f"{name} has shape {shape}, expected (*, {', '.join(map(str, exp))})")
        shape = shape[len(shape) - len(exp):]
    if len(shape) != len(exp):
        raise ShapeError(f"{name} has shape {tuple(array.shape)}, expected {tuple(expected)}")
    symbols: dict[str, int] = {}
    for got, want in zip(shape, exp):
        if want is None:
            continue
        if isinstance(want, str):
            if symbols.setdefault(want, got) != got:
                raise ShapeError(
                    f"{name} has shape {tuple(array.shape)}, expected {tuple(expected)} "
                    f"({want} must be the same everywhere)"
                )
        elif got != want:
            raise ShapeError(f"{name} has shape {tuple(array.shape)}, expected {tuple(expected)}")
