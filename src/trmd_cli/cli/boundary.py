"""The CLI's single error boundary.

Library code raises :class:`~trmd_cli.errors.TrmdError` subclasses; here they become one line on
stderr and exit 2. Anything unexpected becomes one line and exit 1, with the traceback only under
``trmd -v``. Ctrl-C exits 130; outputs are untouched because every writer is atomic.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import TypeVar

import typer
from rich.console import Console

from ..errors import TrmdError

F = TypeVar("F", bound=Callable)

#: stderr console shared by all commands (progress bars, warnings, errors)
err = Console(stderr=True, highlight=False)
#: set by the app callback (``trmd -v``)
state = {"verbose": False}


def warn(message: str) -> None:
    err.print(f"[yellow]warning:[/] {message}", soft_wrap=True)


def fail(message: str, code: int) -> typer.Exit:
    err.print(f"[red]error:[/] {message}", soft_wrap=True, markup=True, emoji=False)
    return typer.Exit(code)


def guarded(fn: F) -> F:
    """Wrap a command so every failure leaves as one clear line and an exit code."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except (typer.Exit, typer.Abort):
            raise
        except TrmdError as e:
            if state["verbose"]:
                err.print_exception()
            raise fail(_escape(str(e)), e.exit_code) from None
        except KeyboardInterrupt:
            raise fail("interrupted; no partial output was left", 130) from None
        except MemoryError:
            raise fail("out of memory; try a smaller --tile or fewer frames at once", 1) from None
        except Exception as e:  # noqa: BLE001 - the boundary is the place for it
            if state["verbose"]:
                err.print_exception()
                raise fail(f"unexpected {type(e).__name__}: {_escape(str(e))}", 1) from None
            raise fail(
                f"unexpected {type(e).__name__}: {_escape(str(e))} "
                "(run `trmd -v …` for the traceback and please report it)",
                1,
            ) from None

    return wrapper  # type: ignore[return-value]


def _escape(text: str) -> str:
    from rich.markup import escape

    return escape(text.splitlines()[0] if text else text)


def progress_enabled() -> bool:
    return sys.stderr.isatty()
