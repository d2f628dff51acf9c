"""The `phalanx` command line. Commands are thin; their work lives in the library."""

from __future__ import annotations

import importlib
import pkgutil

import typer

from phalanx.cli import commands

app = typer.Typer(
    name="phalanx",
    help="Tightly coupled formations of differential-drive robots, forwards and backwards.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _register_commands() -> None:
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"phalanx.cli.commands.{info.name}")
        module.register(app)


_register_commands()


def main() -> None:
    """Entry point of the `phalanx` console script."""
    app()
