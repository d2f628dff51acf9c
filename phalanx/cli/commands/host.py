"""`phalanx host` and `phalanx router`: the long-running processes of a multi-host fleet."""

from __future__ import annotations

import logging
import socket
from typing import TYPE_CHECKING, Annotated

import typer

if TYPE_CHECKING:
    from phalanx.hosts.deployment import LoadedDeployment

DeploymentArg = Annotated[
    str, typer.Argument(help="Deployment file, or the name of one in configs/deployments.")
]


def load_or_exit(deployment: str) -> LoadedDeployment:
    """The validated deployment, or its errors printed and exit code 2."""
    from phalanx.core.errors import ConfigError
    from phalanx.hosts.deployment import load_deployment

    try:
        return load_deployment(deployment)
    except ConfigError as exc:
        typer.echo(str(exc), err=True)
        raise typer.Exit(2) from exc


def host(
    deployment: DeploymentArg,
    name: Annotated[
        str | None, typer.Option(help="This host's name in the deployment (default: hostname).")
    ] = None,
    quiet: Annotated[
        bool, typer.Option(help="Log warnings only; do not copy the children's output.")
    ] = False,
) -> None:
    """Run this host's daemon: spawn, supervise and stop the fleet's processes on request."""
    from phalanx.core.errors import ConfigError, TransportError
    from phalanx.hosts.daemon import DaemonOptions, HostDaemon
    from phalanx.runtime.signals import stop_on_signals

    level = logging.WARNING if quiet else logging.INFO
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(message)s")
    loaded = load_or_exit(deployment)
    here = name or socket.gethostname().split(".")[0]
    try:
        daemon = HostDaemon(loaded, here, DaemonOptions(echo=not quiet))
        daemon.run(stop_on_signals())
    except (ConfigError, TransportError) as exc:
        typer.echo(str(exc), err=True)
        raise typer.Exit(2) from exc


def router(
    deployment: Annotated[
        str | None, typer.Argument(help="Deployment whose [zenoh.router] to serve.")
    ] = None,
    listen: Annotated[
        list[str] | None,
        typer.Option("--listen", help="Endpoint to listen on, e.g. tcp/0.0.0.0:7446 (repeatable)."),
    ] = None,
) -> None:
    """Run a Zenoh router, for hosts that cannot reach each other directly."""
    from phalanx.core.errors import ConfigError, TransportError
    from phalanx.hosts.wiring import router_transport
    from phalanx.runtime.signals import stop_on_signals
    from phalanx.wire.transport import TransportConfig, open_session

    if deployment is None and not listen:
        raise typer.BadParameter("give a deployment file or at least one --listen endpoint")
    try:
        if deployment is not None:
            transport = router_transport(load_or_exit(deployment).spec)
            if listen:
                transport = transport.model_copy(update={"listen": tuple(listen)})
        else:
            transport = TransportConfig(mode="router", listen=tuple(listen or ()))
        stop = stop_on_signals()
        with open_session(transport):
            typer.echo(f"router listening on {', '.join(transport.listen)}")
            stop.wait()
    except (ConfigError, TransportError) as exc:
        typer.echo(str(exc), err=True)
        raise typer.Exit(2) from exc


def register(app: typer.Typer) -> None:
    """Add `phalanx host` and `phalanx router`."""
    app.command("host")(host)
    app.command("router")(router)


__all__ = ["DeploymentArg", "load_or_exit", "register"]
