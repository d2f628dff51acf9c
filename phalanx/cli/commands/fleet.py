"""`phalanx agent`, `phalanx world`, `phalanx up`: robots as processes over Zenoh."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import typer

if TYPE_CHECKING:
    from phalanx.core.config import RobotParams, Scenario
    from phalanx.drivers.base import Driver
    from phalanx.drivers.safety import SafeDriver
    from phalanx.runtime.signals import Stoppable
    from phalanx.telemetry.stream import Telemetry
    from phalanx.wire.messages import AgentReport
    from phalanx.wire.transport import TransportConfig

# `phalanx agent`'s exit code when the world's frames stopped coming (sim driver): not a
# finished run, so a supervisor restarts it and it rejoins once the world is back.
EXIT_WORLD_LOST = 3

ScenarioArg = Annotated[
    Path, typer.Argument(help="Scenario TOML file.", exists=True, dir_okay=False)
]
FleetOpt = Annotated[str, typer.Option(help="Fleet name: the Zenoh key prefix phalanx/<fleet>/.")]
ClockOpt = Annotated[str, typer.Option(help="lockstep (deterministic, fast) or realtime.")]
ListenOpt = Annotated[
    list[str] | None, typer.Option("--listen", help="Zenoh endpoint to listen on.")
]
ConnectOpt = Annotated[
    list[str] | None, typer.Option("--connect", help="Zenoh endpoint to connect to.")
]
ModeOpt = Annotated[str, typer.Option(help="Zenoh mode: peer, client or router.")]
RecordingIdOpt = Annotated[
    str | None, typer.Option(help="Telemetry: the fleet run's Rerun recording id (shared).")
]
TelemetryFileOpt = Annotated[
    Path | None, typer.Option(help="Telemetry: write this process's part to this .rrd.")
]
TelemetryUrlOpt = Annotated[
    str | None,
    typer.Option(help="Telemetry: stream live to this Rerun gRPC url (see phalanx view)."),
]
SetOpt = Annotated[
    list[str] | None,
    typer.Option("--set", help="Override a scenario field, e.g. --set duration_s=60 (repeatable)."),
]


def _scenario(path: Path, overrides: list[str] | None) -> Scenario:
    from phalanx.core.config import apply_overrides, load_scenario

    config = load_scenario(path)
    return apply_overrides(config, overrides) if overrides else config


def _transport(mode: str, listen: list[str] | None, connect: list[str] | None) -> TransportConfig:
    from phalanx.wire.transport import TransportConfig

    if mode not in ("peer", "client", "router"):
        raise typer.BadParameter(f"expected peer, client or router, got {mode!r}")
    return TransportConfig(mode=mode, listen=tuple(listen or ()), connect=tuple(connect or ()))


def _stop_on_signals() -> Stoppable:
    from phalanx.runtime.signals import stop_on_signals

    return stop_on_signals()


def _clock(value: str) -> Literal["lockstep", "realtime"]:
    if value == "lockstep":
        return "lockstep"
    if value == "realtime":
        return "realtime"
    raise typer.BadParameter(f"expected lockstep or realtime, got {value!r}")


def agent(
    scenario: ScenarioArg,
    robot: Annotated[str, typer.Option(help="This process's robot id.")],
    fleet: FleetOpt = "default",
    clock: ClockOpt = "lockstep",
    listen: ListenOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = "peer",
    set_: SetOpt = None,
    driver: Annotated[
        str, typer.Option(help="sim (the world process drives it), arcos or canopen.")
    ] = "sim",
    arcos_port: Annotated[
        str | None, typer.Option(help="arcos: serial device, e.g. /dev/ttyUSB0.")
    ] = None,
    arcos_tcp: Annotated[
        str | None, typer.Option(help="arcos: host:port (MobileSim, emulator: 8101).")
    ] = None,
    baud: Annotated[int, typer.Option(help="arcos: serial baud rate.")] = 9600,
    can_channel: Annotated[str, typer.Option(help="canopen: python-can channel.")] = "can0",
    can_interface: Annotated[
        str, typer.Option(help="canopen: python-can interface (socketcan, virtual...).")
    ] = "socketcan",
    epoch: Annotated[
        float | None,
        typer.Option(
            help="Robot drivers: Unix time of step 0, shared by the fleet (default: now)."
        ),
    ] = None,
    watchdog: Annotated[
        float, typer.Option(help="Robot drivers: stop if no command for this long (s).")
    ] = 0.5,
    frame_timeout: Annotated[
        float,
        typer.Option(
            help="sim driver: give up (exit code 3) after this long without a frame from "
            "the world (s).",
            min=0.1,
        ),
    ] = 30.0,
    recording_id: RecordingIdOpt = None,
    telemetry_file: TelemetryFileOpt = None,
    telemetry_url: TelemetryUrlOpt = None,
) -> None:
    """Run one robot's agent: Zenoh in, behaviour stack, command out."""
    from phalanx.core.config import load_robot

    logging.basicConfig(level=logging.INFO, format=f"%(asctime)s {robot} %(levelname)s %(message)s")
    config = _scenario(scenario, set_)
    if robot not in {r.id for r in config.robots}:
        raise typer.BadParameter(f"robot {robot!r} is not in {scenario}")
    transport = _transport(mode, listen, connect)
    params = load_robot(config.robot)
    stop = _stop_on_signals()
    with _telemetry(recording_id, telemetry_file, telemetry_url, robot) as telemetry:
        report, world_lost = _run_agent(
            robot, config, params, transport, fleet, clock, stop, telemetry,
            _backend(driver, arcos_port, arcos_tcp, baud, can_channel, can_interface),
            epoch, watchdog, frame_timeout,
        )  # fmt: skip
    typer.echo(
        f"{robot}: {report.steps} steps, {report.saturations} saturations, "
        f"{report.dropped_messages} dropped messages"
    )
    if world_lost:  # not a finished run: a supervisor (phalanx host) restarts it to rejoin
        typer.echo(f"{robot}: no frame from the world for {frame_timeout:g} s", err=True)
        raise typer.Exit(EXIT_WORLD_LOST)


def _telemetry(
    recording_id: str | None, path: Path | None, url: str | None, robot_id: str | None
) -> Telemetry:
    from phalanx.telemetry.stream import Telemetry, sink_for

    sink = sink_for(path, url)
    if sink.kind != "off" and recording_id is None:
        raise typer.BadParameter("telemetry needs --recording-id (one per fleet run)")
    return Telemetry(recording_id=recording_id or "off", sink=sink, robot_id=robot_id)


def _run_agent(
    robot: str,
    config: Scenario,
    params: RobotParams,
    transport: TransportConfig,
    fleet: str,
    clock: str,
    stop: Stoppable,
    telemetry: Telemetry,
    backend: Driver | None,
    epoch: float | None,
    watchdog: float,
    frame_timeout_s: float,
) -> tuple[AgentReport, bool]:
    """Run the agent to its end: its report, and whether the world's frames stopped."""
    import time

    from phalanx.runtime.agent import AgentRuntime, RuntimeOptions

    tel = telemetry if telemetry.sink.kind != "off" else None
    if backend is None:
        options = RuntimeOptions(
            fleet=fleet, transport=transport, clock=_clock(clock), frame_timeout_s=frame_timeout_s
        )
        runtime = AgentRuntime(robot, config, params, options, telemetry=tel)
        return runtime.run(stop), runtime.world_lost
    # A robot driver: the agent keeps its own clock; commands go through the safety layer.
    from phalanx.drivers.safety import SafeDriver, SafetyLimits
    from phalanx.runtime.driver_agent import DriverRuntime

    bounds = config.limits
    limits = SafetyLimits(
        bounds.v_max_mps or params.v_max_mps,
        math.radians(bounds.omega_max_degps or params.omega_max_degps),
        watchdog,
    )
    options = RuntimeOptions(fleet=fleet, transport=transport, clock="realtime")
    safe = SafeDriver(backend, limits)
    _connect_with_retry(safe, stop)
    with safe:
        runtime = DriverRuntime(
            robot, config, params, options, safe, epoch_s=epoch or time.time(), telemetry=tel
        )
        return runtime.run(stop), False


def _connect_with_retry(driver: SafeDriver, stop: Stoppable, timeout_s: float = 15.0) -> None:
    """Connect, retrying while the robot (or its emulator) comes up; exit 2 if it never does."""
    import time

    from phalanx.core.errors import DriverError

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            driver.connect()
            return
        except DriverError as exc:
            if time.monotonic() > deadline or stop.wait(0.5):
                typer.echo(f"cannot reach the robot: {exc}", err=True)
                raise typer.Exit(2) from exc


def _backend(
    driver: str,
    arcos_port: str | None,
    arcos_tcp: str | None,
    baud: int,
    can_channel: str,
    can_interface: str,
) -> Driver | None:
    if driver == "sim":
        return None
    if driver == "arcos":
        from phalanx.drivers.arcos import ArcosDriver, ArcosSettings

        try:
            return ArcosDriver(ArcosSettings(port=arcos_port, tcp=arcos_tcp, baud=baud))
        except ValueError as exc:
            raise typer.BadParameter(f"arcos: {exc}") from exc
    if driver == "canopen":
        from phalanx.drivers.canopen import CanopenDriver, CanopenSettings

        return CanopenDriver(CanopenSettings(channel=can_channel, interface=can_interface))
    raise typer.BadParameter(f"driver must be sim, arcos or canopen, got {driver!r}")


def world(
    scenario: ScenarioArg,
    fleet: FleetOpt = "default",
    clock: ClockOpt = "lockstep",
    speed: Annotated[float, typer.Option(min=0.01, help="Real-time speed factor.")] = 1.0,
    listen: ListenOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = "router",
    set_: SetOpt = None,
    out: Annotated[Path | None, typer.Option(help="Results folder.")] = None,
    recording: Annotated[bool, typer.Option(help="Write a Rerun .rrd.")] = True,
    epoch: Annotated[
        float | None, typer.Option(help="Real time: Unix time of tick 0, shared with agents.")
    ] = None,
    recording_id: RecordingIdOpt = None,
    telemetry_file: TelemetryFileOpt = None,
    telemetry_url: TelemetryUrlOpt = None,
) -> None:
    """Run the simulated world for agents in other processes; write the results folder."""
    from phalanx.analysis.report import print_summary
    from phalanx.analysis.results import write_results
    from phalanx.core.config import load_robot
    from phalanx.runtime.world_process import WorldOptions, WorldProcess

    logging.basicConfig(level=logging.INFO, format="%(asctime)s world %(levelname)s %(message)s")
    config = _scenario(scenario, set_)
    transport = _transport(mode, listen, connect)
    options = WorldOptions(
        fleet=fleet, transport=transport, clock=_clock(clock), speed=speed, epoch_s=epoch
    )
    with _telemetry(recording_id, telemetry_file, telemetry_url, None) as telemetry:
        tel = telemetry if telemetry.sink.kind != "off" else None
        process = WorldProcess(config, load_robot(config.robot), options, telemetry=tel)
        run_log = process.run(_stop_on_signals())
    folder = out or Path("results") / f"{config.name}-{config.controller.kind}-up"
    metrics = write_results(run_log, folder, recording=recording)
    metrics_missed = {r: n for r, n in process.missed.items() if n}
    print_summary(metrics)
    if metrics_missed:
        typer.echo(f"missed tick deadlines: {metrics_missed}")
    typer.echo(f"results: {folder}")


def up(
    scenario: ScenarioArg,
    fleet: FleetOpt = "default",
    clock: ClockOpt = "lockstep",
    speed: Annotated[float, typer.Option(min=0.01, help="Real-time speed factor.")] = 1.0,
    out: Annotated[Path | None, typer.Option(help="Results folder.")] = None,
    restart: Annotated[bool, typer.Option(help="Restart crashed agents (with back-off).")] = False,
    timeout: Annotated[float, typer.Option(help="Give up after this many seconds.")] = 600.0,
    recording: Annotated[bool, typer.Option(help="Write a Rerun .rrd.")] = True,
    set_: SetOpt = None,
    driver: Annotated[
        str,
        typer.Option(help="sim, or arcos: every robot an ARCOS emulator moved by the world."),
    ] = "sim",
    viewer: Annotated[
        bool, typer.Option(help="Open the Rerun viewer and stream the run to it live.")
    ] = False,
    telemetry_url: Annotated[
        str | None,
        typer.Option(help="Stream live to a running viewer, e.g. from `phalanx view --web`."),
    ] = None,
) -> None:
    """Start the world and one agent process per robot here; supervise; write results."""
    from phalanx.runtime.local_fleet import (
        UpOptions,
        merge_recordings,
        plan,
        start_viewer,
        supervise,
        telemetry_dir,
    )

    logging.basicConfig(level=logging.INFO, format="%(asctime)s up %(levelname)s %(message)s")
    config = _scenario(scenario, set_)
    out = out or Path("results") / f"{config.name}-{config.controller.kind}-up"
    if viewer and telemetry_url is None:
        telemetry_url = start_viewer()
    options = UpOptions(
        fleet=fleet,
        clock=_clock(clock),
        speed=speed,
        out=out,
        telemetry_url=telemetry_url,
        restart=restart,
        timeout_s=timeout,
        recording=recording,
        overrides=tuple(f"--set={o}" for o in set_ or ()),
        driver=driver,
    )
    if driver not in ("sim", "arcos"):
        raise typer.BadParameter(f"up runs sim or arcos robots, not {driver!r}")
    if driver == "arcos" and options.clock == "lockstep":
        typer.echo("arcos robots keep their own time: running with --clock realtime", err=True)
        options.clock = "realtime"
    code = supervise(plan(scenario, config, options), options, _stop_on_signals())
    parts = sorted(telemetry_dir(out).glob("*.rrd")) if recording else []
    if parts and merge_recordings(parts, out / "run.rrd"):
        typer.echo(f"recording: {out / 'run.rrd'} ({len(parts)} processes merged)")
    raise typer.Exit(code)


def register(app: typer.Typer) -> None:
    """Add `phalanx agent`, `phalanx world` and `phalanx up`."""
    app.command("agent")(agent)
    app.command("world")(world)
    app.command("up")(up)
