"""`phalanx view`: the Rerun viewer, native or served to a browser, with a memory limit."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Annotated

import typer

from phalanx.cli.numbers import PORT_MAX


def rerun_command(
    recordings: list[Path],
    *,
    web: bool,
    bind: str,
    port: int,
    web_port: int,
    memory_limit: str,
) -> list[str]:
    """The `rerun` command line for `phalanx view`."""
    from phalanx.telemetry.sinks import rerun_executable

    argv = [rerun_executable(), "--bind", bind, "--port", str(port)]
    if web:
        argv += ["--serve-web", "--web-viewer-port", str(web_port)]
        argv += ["--server-memory-limit", memory_limit]
    else:
        argv += ["--memory-limit", memory_limit]
    return argv + [str(r) for r in recordings]


def has_display() -> bool:
    """Whether a window can open here: on Linux (and other X11/Wayland systems) only
    with DISPLAY or WAYLAND_DISPLAY set; macOS and Windows always have a desktop.
    """
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def view(
    recordings: Annotated[
        list[Path] | None, typer.Argument(help=".rrd files to open (none: wait for live data).")
    ] = None,
    web: Annotated[
        bool, typer.Option(help="Serve the web viewer over HTTP instead of opening a window.")
    ] = False,
    bind: Annotated[
        str,
        typer.Option(help="Address to listen on; 0.0.0.0 to take data from robots on the network."),
    ] = "127.0.0.1",
    port: Annotated[
        int, typer.Option(help="gRPC port phalanx processes stream to.", min=1, max=PORT_MAX)
    ] = 9876,
    web_port: Annotated[
        int, typer.Option(help="HTTP port of the web viewer.", min=1, max=PORT_MAX)
    ] = 9090,
    memory_limit: Annotated[
        str, typer.Option(help="Drop the oldest data beyond this (e.g. 2GB, 50%).")
    ] = "2GB",
) -> None:
    """Open the viewer. Stream a run to it with `phalanx up ... --telemetry-url URL`."""
    for path in recordings or []:
        if not path.exists():
            raise typer.BadParameter(f"{path}: no such recording")
    if not web and not has_display():
        typer.echo(
            "error: no display here (neither DISPLAY nor WAYLAND_DISPLAY is set), so no "
            "viewer window can open: add --web to serve the viewer to a browser instead",
            err=True,
        )
        raise typer.Exit(2)
    argv = rerun_command(
        list(recordings or []),
        web=web,
        bind=bind,
        port=port,
        web_port=web_port,
        memory_limit=memory_limit,
    )
    host = "127.0.0.1" if bind in ("0.0.0.0", "::") else bind  # noqa: S104 - compared, not bound
    url = f"rerun+http://{host}:{port}/proxy"
    typer.echo(f"stream to: --telemetry-url {url}", err=True)
    if web:
        typer.echo(f"open: http://{host}:{web_port}/?url={url}", err=True)
    process = subprocess.Popen(argv)  # noqa: S603 - rerun's CLI, our arguments
    signal.signal(signal.SIGTERM, lambda *_: process.terminate())
    try:
        raise typer.Exit(process.wait())
    except KeyboardInterrupt:
        process.terminate()
        raise typer.Exit(process.wait(10)) from None


def register(app: typer.Typer) -> None:
    """Add `phalanx view`."""
    app.command("view")(view)
