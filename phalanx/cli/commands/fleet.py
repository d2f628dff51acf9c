"""`phalanx agent`, `phalanx world`: robots as processes over Zenoh (`phalanx up` starts
them all on this machine: `phalanx.cli.commands.up`).
"""

from __future__ import annotations

import difflib
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal, NoReturn

import typer

from phalanx.cli.commands.run import DpiOpt, FormatOpt

if TYPE_CHECKING:
    from phalanx.analysis.figures import FigureFormat
    from phalanx.analysis.results import ResultsNotWritten
    from phalanx.core.config import Scenario
    from phalanx.core.robot_params import RobotParams
    from phalanx.core.runlog import RunLog
    from phalanx.drivers.base import Driver
    from phalanx.runtime.signals import Stoppable
    from phalanx.runtime.world_process import WorldProcess
    from phalanx.telemetry.stream import Telemetry
    from phalanx.wire.transport import TransportConfig


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
LowLatencyOpt = Annotated[
    bool,
    typer.Option(
        "--lowlatency",
        help="Zenoh's low-latency transport (no priorities, messages under 64 KiB): for a "
        "fleet on one machine joined through a router, as phalanx up runs it (a large "
        "mesh of peers on it can hang Zenoh's declarations).",
    ),
]
TlsCaOpt = Annotated[str | None, typer.Option(help="tls/ endpoints: the fleet CA's certificate.")]
TlsCertOpt = Annotated[str | None, typer.Option(help="tls/ endpoints: this process's certificate.")]
TlsKeyOpt = Annotated[str | None, typer.Option(help="tls/ endpoints: this process's key.")]
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
    from phalanx.core.config_files import apply_overrides, load_scenario

    config = load_scenario(path)
    return apply_overrides(config, overrides, source=str(path)) if overrides else config


def _transport(
    mode: str,
    listen: list[str] | None,
    connect: list[str] | None,
    tls: tuple[str | None, str | None, str | None] = (None, None, None),
    *,
    lowlatency: bool = False,
) -> TransportConfig:
    from phalanx.cli.style import choice
    from phalanx.wire.security import TlsFiles
    from phalanx.wire.transport import TransportConfig

    choice(mode, ("peer", "client", "router"), option="--mode")
    files = None
    if any(tls):
        ca, cert, key = tls
        if ca is None or cert is None or key is None:
            raise typer.BadParameter("give --tls-ca, --tls-cert and --tls-key together")
        files = TlsFiles(ca=ca, cert=cert, key=key)
    return TransportConfig(
        mode=mode,
        listen=tuple(listen or ()),
        connect=tuple(connect or ()),
        tls=files,
        lowlatency=lowlatency,
    )


def _stop_on_signals() -> Stoppable:
    from phalanx.runtime.signals import die_with_parent, stop_on_signals

    stop = stop_on_signals()
    die_with_parent()  # a supervised process stops when its supervisor dies
    return stop


def _clock(value: str) -> Literal["lockstep", "realtime"]:
    from phalanx.cli.style import choice

    choice(value, ("lockstep", "realtime"), option="--clock")
    return "lockstep" if value == "lockstep" else "realtime"


def agent(
    scenario: ScenarioArg,
    robot: Annotated[str, typer.Option(help="This process's robot id.")],
    fleet: FleetOpt = "default",
    clock: ClockOpt = "lockstep",
    listen: ListenOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = "peer",
    lowlatency: LowLatencyOpt = False,
    tls_ca: TlsCaOpt = None,
    tls_cert: TlsCertOpt = None,
    tls_key: TlsKeyOpt = None,
    set_: SetOpt = None,
    driver: Annotated[
        str,
        typer.Option(help="sim (the world process moves the robot) or a driver: arcos, canopen."),
    ] = "sim",
    driver_setting: Annotated[
        list[str] | None,
        typer.Option(
            "--driver-setting",
            help="A setting of the driver, KEY=VALUE (VALUE in TOML), e.g. "
            "--driver-setting bitrate=250000 (repeatable).",
        ),
    ] = None,
    arcos_port: Annotated[
        str | None, typer.Option(help="arcos: serial device, e.g. /dev/ttyUSB0.")
    ] = None,
    arcos_tcp: Annotated[
        str | None, typer.Option(help="arcos: host:port (MobileSim, emulator: 8101).")
    ] = None,
    baud: Annotated[
        int | None, typer.Option(help="arcos: serial baud rate (default: 9600).")
    ] = None,
    can_channel: Annotated[
        str | None, typer.Option(help="canopen: python-can channel (default: can0).")
    ] = None,
    can_interface: Annotated[
        str | None,
        typer.Option(help="canopen: python-can interface: socketcan (default), virtual..."),
    ] = None,
    epoch: Annotated[
        float | None,
        typer.Option(
            help="Robot drivers: Unix time of step 0, shared by the fleet (default: now)."
        ),
    ] = None,
    watchdog: Annotated[
        float, typer.Option(help="Robot drivers: stop if no command for this long (s).")
    ] = 0.5,
    camera: Annotated[
        str | None,
        typer.Option(
            help="Robot drivers: a camera reading the other robots' fiducial markers, "
            "DEVICE=CALIBRATION.toml (e.g. /dev/video0=cam.toml)."
        ),
    ] = None,
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
    from phalanx.core.config_files import load_robot

    logging.basicConfig(level=logging.INFO, format=f"%(asctime)s {robot} %(levelname)s %(message)s")
    config = _scenario(scenario, set_)
    if robot not in {r.id for r in config.robots}:
        raise typer.BadParameter(f"robot {robot!r} is not in {scenario}")
    transport = _transport(
        mode, listen, connect, (tls_ca, tls_cert, tls_key), lowlatency=lowlatency
    )
    params = load_robot(config.robot)
    shortcuts = {
        "--arcos-port": arcos_port,
        "--arcos-tcp": arcos_tcp,
        "--baud": baud,
        "--can-channel": can_channel,
        "--can-interface": can_interface,
    }
    backend = _backend(driver, params, shortcuts=shortcuts, settings=driver_setting)
    from phalanx.core.errors import DriverUnavailable
    from phalanx.runtime.agent_process import AgentProcess, run_agent

    process = AgentProcess(
        robot_id=robot, fleet=fleet, transport=transport, clock=_clock(clock), epoch_s=epoch,
        watchdog_s=watchdog, frame_timeout_s=frame_timeout, camera=camera,
    )  # fmt: skip
    stop = _stop_on_signals()
    with _telemetry(recording_id, telemetry_file, telemetry_url, robot) as telemetry:
        tel = telemetry if telemetry.sink.kind != "off" else None
        try:
            report, code = run_agent(
                process, config, params, driver=backend, stop=stop, telemetry=tel
            )
        except DriverUnavailable as exc:
            typer.echo(str(exc), err=True)
            raise typer.Exit(2) from exc
    typer.echo(
        f"{robot}: {report.steps} steps, {report.saturations} saturations, "
        f"{report.dropped_messages} dropped messages"
    )
    if code:  # not a finished run: a supervisor (phalanx host) restarts it to rejoin
        from phalanx.runtime.exits import EXIT_WORLD_LOST, agent_exit_reason

        why = agent_exit_reason(code)
        if code == EXIT_WORLD_LOST:
            why = f"no frame from the world for {frame_timeout:g} s"
        typer.echo(f"{robot}: {why} (exit code {code}, not a finished run)", err=True)
        raise typer.Exit(code)


def _telemetry(
    recording_id: str | None, path: Path | None, url: str | None, robot_id: str | None
) -> Telemetry:
    from phalanx.telemetry.sinks import sink_for
    from phalanx.telemetry.stream import Telemetry

    sink = sink_for(path, url)
    if sink.kind != "off" and recording_id is None:
        raise typer.BadParameter("telemetry needs --recording-id (one per fleet run)")
    # (the world's and agents' control loops come first: the telemetry thread yields)
    return Telemetry(
        recording_id=recording_id or "off", sink=sink, robot_id=robot_id, background=True
    )


# The documented shortcut options: each fills one field of one backend's settings.
_SHORTCUTS = {
    "--arcos-port": ("arcos", "port"),
    "--arcos-tcp": ("arcos", "tcp"),
    "--baud": ("arcos", "baud"),
    "--can-channel": ("canopen", "channel"),
    "--can-interface": ("canopen", "interface"),
}


def _backend(
    driver: str,
    robot: RobotParams,
    *,
    shortcuts: Mapping[str, object],
    settings: list[str] | None,
) -> Driver | None:
    """The robot's driver, not yet connected; None for sim (the world moves the robot).

    Its settings are the shortcut options given (`shortcuts`, None: not given) and the
    `--driver-setting KEY=VALUE` pairs, checked by the backend's own settings model.
    """
    from phalanx.core.errors import ConfigError, DriverUnavailable
    from phalanx.drivers import backend_names, open_driver

    names = ("sim", *backend_names())
    if driver not in names:
        close = difflib.get_close_matches(driver, names, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise typer.BadParameter(
            f"expected one of {', '.join(names)}, got {driver!r}{hint}", param_hint="'--driver'"
        )
    values: dict[str, object] = {}
    for option, value in shortcuts.items():
        if value is None:
            continue
        owner, field = _SHORTCUTS[option]
        if owner != driver:
            raise typer.BadParameter(f"{option} is an option of --driver {owner}, not {driver}")
        values[field] = value
    pairs = _driver_settings(settings or [])
    if driver == "sim":
        if pairs:
            raise typer.BadParameter("--driver-setting: the sim driver has no settings")
        return None
    for key, value in pairs.items():
        if key in values:
            raise typer.BadParameter(f"{key!r} given twice: by an option and by --driver-setting")
        values[key] = value
    try:
        return open_driver(driver, values, robot=robot)
    except ConfigError as exc:
        raise typer.BadParameter(str(exc)) from exc
    except DriverUnavailable as exc:
        typer.echo(f"driver {driver!r}: {exc}", err=True)
        raise typer.Exit(2) from exc


def _driver_settings(pairs: list[str]) -> dict[str, object]:
    """`KEY=VALUE` pairs, VALUE a TOML value (a bare word is a string, as with --set)."""
    from phalanx.core.config_files import parse_value

    values: dict[str, object] = {}
    for pair in pairs:
        key, sep, text = (part.strip() for part in pair.partition("="))
        if not sep or not key:
            raise typer.BadParameter(
                f"expected KEY=VALUE, got {pair!r}", param_hint="'--driver-setting'"
            )
        values[key] = parse_value(text)
    return values


def world(
    scenario: ScenarioArg,
    fleet: FleetOpt = "default",
    clock: ClockOpt = "lockstep",
    speed: Annotated[float, typer.Option(min=0.01, help="Real-time speed factor.")] = 1.0,
    listen: ListenOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = "router",
    lowlatency: LowLatencyOpt = False,
    tls_ca: TlsCaOpt = None,
    tls_cert: TlsCertOpt = None,
    tls_key: TlsKeyOpt = None,
    set_: SetOpt = None,
    out: Annotated[Path | None, typer.Option(help="Results folder.")] = None,
    recording: Annotated[bool, typer.Option(help="Write a Rerun .rrd.")] = True,
    epoch: Annotated[
        float | None, typer.Option(help="Real time: Unix time of tick 0, shared with agents.")
    ] = None,
    recording_id: RecordingIdOpt = None,
    telemetry_file: TelemetryFileOpt = None,
    telemetry_url: TelemetryUrlOpt = None,
    observe: Annotated[
        list[str] | None,
        typer.Option(
            "--observe",
            help="A robot that moves on its own (a real driver, AMRISim): recorded from its "
            "true pose, motion capture or its own estimate, not simulated (repeatable; "
            "needs --clock realtime and --epoch).",
        ),
    ] = None,
    figure_format: FormatOpt = "png",
    dpi: DpiOpt = 150,
) -> None:
    """Run the world for agents in other processes: simulate the robots on the sim
    driver, record the ones that move on their own; write the results folder (and, while
    the run goes on, a checkpoint of it every few seconds). Exit code 0 for a complete
    run, 5 for one its results mark incomplete, 6 if the results could not be written.
    """
    from phalanx.analysis.results import ResultsNotWritten, write_checkpoint
    from phalanx.cli.commands.run import _figure_format
    from phalanx.core.config_files import load_robot
    from phalanx.runtime.exits import EXIT_INCOMPLETE
    from phalanx.runtime.world_process import WorldOptions, WorldProcess

    fmt = _figure_format(figure_format)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s world %(levelname)s %(message)s")
    config = _scenario(scenario, set_)
    transport = _transport(
        mode, listen, connect, (tls_ca, tls_cert, tls_key), lowlatency=lowlatency
    )
    options = WorldOptions(
        fleet=fleet, transport=transport, clock=_clock(clock), speed=speed, epoch_s=epoch,
        observed=tuple(observe or ()),
    )  # fmt: skip
    folder = out or Path("results") / f"{config.name}-{config.controller.kind}-up"
    with _telemetry(recording_id, telemetry_file, telemetry_url, None) as telemetry:
        tel = telemetry if telemetry.sink.kind != "off" else None
        process = WorldProcess(
            config, load_robot(config.robot), options, telemetry=tel,
            checkpoint=lambda so_far: write_checkpoint(so_far, folder),
        )  # fmt: skip
        run_log = process.run(_stop_on_signals())
    try:
        complete = _write_world_results(
            process, run_log, folder, recording=recording, figure_format=fmt, dpi=dpi
        )
    except ResultsNotWritten as exc:
        _results_lost(exc)
    typer.echo(f"results: {folder}")
    if not complete:
        raise typer.Exit(EXIT_INCOMPLETE)


def _write_world_results(
    process: WorldProcess,
    run_log: RunLog,
    folder: Path,
    *,
    recording: bool,
    figure_format: FigureFormat = "png",
    dpi: int = 150,
) -> bool:
    """The world's results folder, its summary printed; whether the run is complete."""
    from phalanx.analysis.report import print_summary
    from phalanx.analysis.results import mark_results, write_results

    metrics = write_results(
        run_log, folder, recording=recording, figure_format=figure_format, dpi=dpi
    )
    marked = mark_results(folder, problems=[])
    print_summary(metrics)
    missed = {r: n for r, n in process.missed.items() if n}
    if missed:
        typer.echo(f"missed tick deadlines: {missed}")
    if not marked["complete"]:
        typer.echo(f"incomplete run: {marked['incomplete_reason']}")
    return bool(marked["complete"])


def _results_lost(exc: ResultsNotWritten) -> NoReturn:
    """One message for results that could not be written (a full disk), and exit 6."""
    from phalanx.runtime.exits import EXIT_RESULTS_LOST

    typer.echo(f"error: {exc}", err=True)
    raise typer.Exit(EXIT_RESULTS_LOST) from exc


def register(app: typer.Typer) -> None:
    """Add `phalanx agent` and `phalanx world` (`phalanx up` is in `commands.up`)."""
    app.command("agent")(agent)
    app.command("world")(world)
