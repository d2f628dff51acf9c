"""`phalanx mocap`: a motion-capture system's rigid bodies as pose fixes on the fleet."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Annotated

import typer

from phalanx.cli.numbers import seconds_or_ever
from phalanx.cli.style import choice

# The backends of libmotioncapture (the `motioncapture` package); a build may lack some.
MOCAP_SYSTEMS = (
    "optitrack",
    "optitrack_closed_source",
    "vicon",
    "qualisys",
    "nokov",
    "vrpn",
    "motionanalysis",
    "fzmotion",
    "mock",
)


def mocap(
    scenario: Annotated[Path, typer.Argument(help="Scenario file: robots, [localisation.mocap].")],
    system: Annotated[
        str, typer.Option(help=f"motioncapture backend: {', '.join(MOCAP_SYSTEMS)}.")
    ] = "optitrack",
    host: Annotated[str | None, typer.Option(help="The mocap server's address.")] = None,
    setting: Annotated[
        list[str] | None,
        typer.Option(
            "--setting",
            help="Backend setting KEY=VALUE (repeatable), e.g. for mock "
            "rigid_bodies='r1(1,2,0,1,0,0,0)' (x, y, z, qw, qx, qy, qz).",
        ),
    ] = None,
    body: Annotated[
        list[str] | None,
        typer.Option("--body", help="Rigid body NAME=ROBOT (repeatable; beside the scenario's)."),
    ] = None,
    origin: Annotated[
        str, typer.Option(help="The mocap frame's origin in the world frame: x_m,y_m,yaw_deg.")
    ] = "0,0,0",
    fleet: Annotated[str, typer.Option(help="Fleet name.")] = "default",
    mode: Annotated[str, typer.Option(help="Zenoh mode: peer, client, router.")] = "client",
    connect: Annotated[list[str] | None, typer.Option("--connect", help="Zenoh endpoint.")] = None,
    listen: Annotated[list[str] | None, typer.Option("--listen", help="Zenoh endpoint.")] = None,
    duration: Annotated[
        float, typer.Option(help="Stop after this many seconds.", callback=seconds_or_ever)
    ] = math.inf,
) -> None:
    """Publish a motion-capture system's rigid bodies as pose fixes (robot/<id>/fix)."""
    from phalanx.core.config_files import load_scenario
    from phalanx.core.errors import DriverError
    from phalanx.core.geometry import Pose2D
    from phalanx.core.localisation import MocapSource
    from phalanx.runtime.mocap_bridge import MocapBridge, MocapOptions, body_map
    from phalanx.runtime.signals import stop_on_signals
    from phalanx.wire.transport import TransportConfig, open_session

    choice(system, MOCAP_SYSTEMS, option="--system")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s mocap %(levelname)s %(message)s")
    config = load_scenario(scenario)
    source = config.localisation.mocap or MocapSource()
    robots = tuple(r.id for r in config.robots)
    settings = dict(pair.partition("=")[::2] for pair in setting or [])
    if host is not None:
        settings["hostname"] = host
    try:
        bodies = body_map(source.bodies, robots, list(body or []))
        x, y, yaw = (float(v) for v in origin.split(","))
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    options = MocapOptions(
        system=system,
        settings=settings,
        bodies=bodies,
        std_m=source.std_m,
        std_rad=math.radians(source.std_deg),
        latency_s=source.latency_s,
        origin=Pose2D(x, y, math.radians(yaw)),
    )
    bridge = MocapBridge(options, fleet)
    stop = stop_on_signals()
    transport = TransportConfig(mode=mode, listen=tuple(listen or ()), connect=tuple(connect or ()))
    try:
        bridge.connect()
        with open_session(transport) as session:
            bridge.run(session, stop, duration_s=duration)
    except DriverError as exc:
        why = str(exc)
        if "Unknown motion capture type" in why:  # (libmotioncapture's own words)
            why = f"--system {system}: this build of the motioncapture library lacks it"
        typer.echo(f"mocap: {why}", err=True)
        raise typer.Exit(2) from exc
    s = bridge.stats
    typer.echo(
        f"mocap: {s.frames} frames, {s.published} fixes, {s.lost} lost, {s.unmapped} unmapped",
        err=True,
    )


def register(app: typer.Typer) -> None:
    """Add `phalanx mocap`."""
    app.command("mocap")(mocap)
