"""The `phalanx` command line. Commands are thin; their work lives in the library.

A mistake in what the user gave (a configuration or deployment file, a `--set` value, a
file that is not TOML or not text) ends a command with one message naming the file, the
field and the fix, and exit code 2; `--debug` shows the traceback as well. How the
command line presents itself (verbs by task, help as written) is `phalanx.cli.style`.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
from collections.abc import Callable
from typing import Annotated

import typer

from phalanx.cli import commands
from phalanx.cli.style import PhalanxGroup, use_everywhere

EXIT_USAGE = 2  # the user's input is wrong (click's own code for usage errors)
EXIT_FAILED = 1  # the command ran and failed

app = typer.Typer(
    name="phalanx",
    help="Tightly coupled formations of differential-drive robots, forwards and backwards.",
    no_args_is_help=True,
    add_completion=True,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
    cls=PhalanxGroup,
    context_settings={"help_option_names": ["-h", "--help"]},
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
    use_everywhere(app)


_register_commands()


def _profiled(run: Callable[[], None], folder: str) -> None:
    """Run under cProfile (the main thread) and write `<command>-<pid>.prof` in `folder`:
    how the multi-process path is profiled, one file per process of a fleet.
    """
    import cProfile
    import os

    command = next((a for a in sys.argv[1:] if not a.startswith("-")), "phalanx")
    profile = cProfile.Profile()
    try:
        profile.runcall(run)
    finally:
        profile.dump_stats(os.path.join(folder, f"{command}-{os.getpid()}.prof"))


def main() -> None:
    """Entry point of the `phalanx` console script (`PHALANX_PROFILE=<folder>` profiles it)."""
    import os

    from phalanx.core.errors import ConfigError, DeploymentError, PhalanxError

    folder = os.environ.get("PHALANX_PROFILE")
    try:
        if folder:
            _profiled(app, folder)
        else:
            app()
    except PhalanxError as exc:
        if _options["debug"]:
            raise
        sys.stderr.write(f"error: {exc}\n")
        usage = isinstance(exc, ConfigError | DeploymentError)
        sys.exit(EXIT_USAGE if usage else EXIT_FAILED)
