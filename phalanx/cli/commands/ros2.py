"""`phalanx ros2`: a fleet's robots as ROS 2 topics over rmw_zenoh (docs/ROS2.md)."""

from __future__ import annotations

import contextlib
import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import typer

from phalanx.cli.numbers import seconds_or_ever

if TYPE_CHECKING:
    from phalanx.core.config import Ros2Config, Scenario
    from phalanx.wire.transport import FleetSession, TransportConfig

ScenarioArg = Annotated[
    Path | None,
    typer.Argument(help="Scenario file (its robots, formation, world and [ros2]).", dir_okay=False),
]
DeploymentOpt = Annotated[
    str | None,
    typer.Option(help="Deployment file or name: fleet, scenario, [ros2] and the host to join."),
]
ListOpt = Annotated[list[str] | None, typer.Option(help="Zenoh endpoint (repeatable).")]


def ros2(
    scenario: ScenarioArg = None,
    deployment: DeploymentOpt = None,
    fleet: Annotated[str, typer.Option(help="Fleet name.")] = "default",
    mode: Annotated[str, typer.Option(help="Zenoh mode: peer or client.")] = "peer",
    connect: ListOpt = None,
    listen: ListOpt = None,
    lowlatency: Annotated[
        bool, typer.Option(help="Zenoh's low-latency transport, as the fleet's processes use it.")
    ] = False,
    identity: Annotated[
        str | None,
        typer.Option(help="A deployment's TLS identity (default: viewer.<[ros2] identity>)."),
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="Override a scenario field, e.g. --set ros2.domain_id=3."),
    ] = None,
    duration: Annotated[
        float, typer.Option(help="Stop after this many seconds.", callback=seconds_or_ever)
    ] = math.inf,
    ros_connect: Annotated[
        list[str] | None,
        typer.Option(
            help="Endpoint of ROS 2's Zenoh router, joined by a session of its own "
            "(repeatable; default: [ros2] connect; none: ROS 2 on the fleet's session)."
        ),
    ] = None,
) -> None:
    """Publish a fleet's robots to ROS 2 over rmw_zenoh's keys (odom, TF, sonar, markers),
    and pass ROS 2's cmd_vel and goal_pose on to the robot that leads.

    Give the scenario and the fleet's endpoints (`--connect` the fleet's router and, for
    ROS 2 tools, rmw_zenoh's router, or `--ros-connect` it), or a deployment. Stops on
    Ctrl-C or SIGTERM.
    """
    from phalanx.core.config_files import apply_overrides, load_robot, load_scenario
    from phalanx.core.errors import ConfigError
    from phalanx.ros2.bridge import Bridge
    from phalanx.runtime.signals import stop_on_signals
    from phalanx.wire.transport import TransportConfig, open_session

    logging.basicConfig(level=logging.INFO, format="%(asctime)s ros2 %(levelname)s %(message)s")
    if (scenario is None) == (deployment is None):
        raise ConfigError("give a scenario file or --deployment, one of the two")
    if deployment is not None:
        config, cfg, fleet, transport = _from_deployment(deployment, identity)
    elif scenario is not None:
        config = load_scenario(scenario)
        cfg = config.ros2
        transport = TransportConfig(
            mode=_mode(mode), listen=tuple(listen or ()), connect=tuple(connect or ()),
            lowlatency=lowlatency,
        )  # fmt: skip
    if set_:
        config = apply_overrides(config, list(set_), source="--set")
        cfg = config.ros2 if deployment is None else cfg
    stop = stop_on_signals()
    ros_endpoints = tuple(ros_connect or ()) or cfg.connect
    with contextlib.ExitStack() as stack:
        session = stack.enter_context(open_session(transport))
        ros: FleetSession | None = None
        if ros_endpoints:  # (a peer: it waits for the router, and meets the nodes directly)
            ros = stack.enter_context(open_session(TransportConfig(connect=ros_endpoints)))
        bridge = Bridge(
            session, fleet=fleet, scenario=config, robot=load_robot(config.robot), cfg=cfg,
            ros=ros,
        )  # fmt: skip
        typer.echo(
            f"ros2: node {bridge.node_token}, {len(bridge.topics)} topics out, "
            f"{len(bridge.inputs)} in",
            err=True,
        )
        bridge.run(stop, duration_s=duration)
    s = bridge.stats
    refused = f", {sum(s.refused.values())} refused ({s.last_refusal})" if s.refused else ""
    typer.echo(
        f"ros2: {s.rounds} rounds, {sum(s.heard.values())} messages in, "
        f"{sum(s.sent.values())} out{refused}, {s.cpu_s:.2f} s CPU",
        err=True,
    )


def _mode(name: str) -> Literal["peer", "client"]:
    from phalanx.cli.style import choice

    choice(name, ("peer", "client"), option="--mode")
    return "client" if name == "client" else "peer"


def _from_deployment(
    name: str, identity: str | None
) -> tuple[Scenario, Ros2Config, str, TransportConfig]:
    """The scenario, `[ros2]`, fleet and transport of the bridge of deployment `name`."""
    from phalanx.hosts.deployment import Ros2Bridge, load_deployment
    from phalanx.hosts.pki import common_name
    from phalanx.hosts.wiring import client_identity, client_transport

    loaded = load_deployment(name)
    spec = loaded.spec
    bridge = spec.ros2 or Ros2Bridge()
    via = bridge.host or (spec.world.host if spec.world is not None else spec.hosts[0].name)
    chosen = identity or common_name("viewer", bridge.identity)
    transport = client_transport(spec, via=via, tls=client_identity(loaded, chosen))
    return loaded.scenario, bridge, spec.fleet, transport


def register(app: typer.Typer) -> None:
    """Add `phalanx ros2`."""
    app.command("ros2")(ros2)
