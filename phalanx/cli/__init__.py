"""The `phalanx` command line. Commands are thin; their work lives in the library.

A mistake in what the user gave (a configuration or deployment file, a `--set` value, a
file that is not TOML or not text) ends a command with one message naming the file, the
field and the fix, and exit code 2; `--debug` shows the traceback as well.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
from typing import Annotated

import typer

from phalanx.cli import commands

EXIT_USAGE = 2  # the user's input is wrong (click's own code for usage errors)
EXIT_FAILED = 1  # the command ran and failed

app = typer.Typer(
    name="phalanx",
    help="Tightly coupled formations of differential-drive robots, forwards and backwards.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
_options = {"debug": False}


@app.callback()
def _global(
    debug: Annotated[
        bool, typer.Option("--debug", help="Show tracebacks of errors (for bug reports).")
    ] = False,
) -> None:
    """Tightly coupled formations of differential-drive robots, forwards and backwards."""
    _options["debug"] = debug


def _register_commands() -> None:
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"phalanx.cli.commands.{info.name}")
        module.register(app)


_register_commands()


def main() -> None:
    """Entry point of the `phalanx` console script."""
    from phalanx.core.errors import ConfigError, DeploymentError, PhalanxError

    try:
        app()
    except PhalanxError as exc:
        if _options["debug"]:
            raise
        sys.stderr.write(f"error: {exc}\n")
        usage = isinstance(exc, ConfigError | DeploymentError)
        sys.exit(EXIT_USAGE if usage else EXIT_FAILED)
