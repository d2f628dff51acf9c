"""`phalanx emulate p3dx`: the robot side of ARCOS on a pty or TCP port."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from phalanx.cli.numbers import PORT_MAX, finite_epoch, seconds

if TYPE_CHECKING:
    from phalanx.core.motion import Body


def emulate(
    model: Annotated[str, typer.Argument(help="Robot model: p3dx.")] = "p3dx",
    pty: Annotated[bool, typer.Option("--pty", help="Serve on a new pseudo-terminal.")] = False,
    tcp: Annotated[
        int | None,
        typer.Option(
            "--tcp", help="Serve on this TCP port (MobileSim: 8101).", min=0, max=PORT_MAX
        ),
    ] = None,
    host: Annotated[str, typer.Option(help="TCP address to bind.")] = "127.0.0.1",
    subtype: Annotated[str, typer.Option(help="p3dx-sh or p3dx (conversion factors).")] = (
        "p3dx-sh"
    ),
    watchdog: Annotated[float, typer.Option(help="Firmware watchdog (s).", callback=seconds)] = 2.0,
    world: Annotated[
        Path | None,
        typer.Option(help="Scenario whose world process moves this robot (with --robot)."),
    ] = None,
    robot: Annotated[str | None, typer.Option(help="Robot id in the world.")] = None,
    fleet: Annotated[str, typer.Option(help="Fleet name (with --world).")] = "default",
    connect: Annotated[
        list[str] | None, typer.Option("--connect", help="Zenoh endpoint (with --world).")
    ] = None,
    epoch: Annotated[
        float | None,
        typer.Option(
            help="Unix time of the run's step 0 (with --world): frames count from it.",
            callback=finite_epoch,
        ),
    ] = None,
    odometry_errors: Annotated[
        Path | None,
        typer.Option(
            help="Stand-alone: report odometry with this scenario's wheel errors "
            "([localisation.odometry])."
        ),
    ] = None,
) -> None:
    """Emulate a robot: stand-alone, or moved by a world process over Zenoh."""
    from phalanx.core.config_files import load_robot, load_scenario
    from phalanx.runtime.arcos_bridge import WorldBody, WorldBridge
    from phalanx.runtime.signals import stop_on_signals
    from phalanx.simulator.arcos_emulator import ArcosEmulator, EmulatorOptions, PtyLink, TcpLink
    from phalanx.wire.transport import TransportConfig

    if model != "p3dx":
        raise typer.BadParameter(f"only p3dx is emulated, not {model!r}")
    if pty == (tcp is not None):
        raise typer.BadParameter("give exactly one of --pty or --tcp PORT")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s emulator %(levelname)s %(message)s")
    params = load_robot(model)
    body: Body | None = None  # stand-alone: the emulator's own, able to brake at its tops
    bridge = None
    if world is not None:
        if robot is None:
            raise typer.BadParameter("--world needs --robot")

        scenario = load_scenario(world)
        body = WorldBody(params, scenario.start_pose(robot), epoch_s=epoch)
        transport = TransportConfig(mode="client", connect=tuple(connect or ()))
        bridge = WorldBridge(body, robot, fleet).open(transport)
    link = PtyLink() if pty else TcpLink(tcp or 8101, host)
    stop = stop_on_signals()
    options = EmulatorOptions(subtype=subtype, watchdog_s=watchdog)
    if odometry_errors is not None and bridge is None:
        errors_from = load_scenario(odometry_errors)
        options.odometry_errors, options.seed = errors_from.localisation.odometry, errors_from.seed
    try:
        with ArcosEmulator(link, params, options, body) as emulator:
            where = link.device if isinstance(link, PtyLink) else f"{link.host}:{link.port}"
            typer.echo(f"emulated {model} ({subtype}) on {where}", err=True)
            while not stop.wait(0.2):
                if isinstance(body, WorldBody) and body.final.is_set():
                    break
            typer.echo(
                f"emulator: {emulator.stats.frames} frames, {emulator.stats.sips_sent} SIPs, "
                f"{emulator.stats.watchdog_stops} watchdog stops",
                err=True,
            )
    finally:
        if bridge is not None:
            time.sleep(0.05)
            bridge.close()


def register(app: typer.Typer) -> None:
    """Add `phalanx emulate`."""
    app.command("emulate")(emulate)
