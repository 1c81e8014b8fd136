"""The ``trmd`` Typer app: global options and command registration.

Each command lives in its own small module under ``trmd_cli.cli`` exposing ``register(app)``;
modules import heavy libraries (torch) inside the command body so ``trmd --help`` is instant.
"""

from __future__ import annotations

import importlib
from typing import Annotated, Optional

import typer

from .. import __version__
from .boundary import state

app = typer.Typer(
    name="trmd",
    help="Deblur event-camera frames: a blurry frame + the events of its exposure → 2N+1 sharp "
    "frames (by default TRMD and the deconvolution along the events' motion, fused; or "
    "either alone, or EDI).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)

#: command modules, in the order `trmd --help` lists them
COMMANDS = ("deblur", "hfr", "motion", "info", "voxelize", "convert", "simulate", "train",
            "finetune", "eval")


def _version(value: bool) -> None:
    if value:
        typer.echo(f"trmd {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Show tracebacks.")] = False,
    version: Annotated[
        Optional[bool],
        typer.Option("--version", callback=_version, is_eager=True, help="Print the version."),
    ] = None,
) -> None:
    state["verbose"] = verbose


# a command module that fails to import is a broken installation: let it fail loudly
for _name in COMMANDS:
    importlib.import_module(f"{__package__}.{_name}").register(app)


def main() -> None:
    from ..heap import tune_memory

    tune_memory()  # a frame's temporaries reuse the heap's pages (see trmd_cli.heap)
    app()


if __name__ == "__main__":
    main()
