"""`phalanx agent`, `phalanx world`: robots as processes over Zenoh (`phalanx up` starts
them all on this machine: `phalanx.cli.commands.up`). `phalanx agent` only turns its
options into a spec (`phalanx.runtime.process_spec`); the runtime builds the agent.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal, NoReturn, TypeVar

import typer

from phalanx.cli.commands.run import DpiOpt, FormatOpt
from phalanx.cli.numbers import finite_epoch, speed_factor
from phalanx.cli.outputs import fresh_folder, results_name

if TYPE_CHECKING:
    from phalanx.analysis.figure_files import FigureFormat
    from phalanx.analysis.results import ResultsNotWritten
    from phalanx.core.config import Scenario
    from phalanx.core.runlog import RunLog
    from phalanx.runtime.process_spec import AgentSpec, TelemetryTarget
    from phalanx.runtime.signals import Stoppable
    from phalanx.runtime.world_process import WorldProcess
    from phalanx.wire.transport import TransportConfig

T = TypeVar("T")


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


AGENT_SPEC_HELP = (
    "The whole agent as a spec, a JSON file as --print-spec writes it (- reads it from "
    "standard input, as phalanx up and the host daemons hand it): no other option is "
    "given with it but --robot and --fleet, which must be the spec's."
)


def agent(
    ctx: typer.Context,
    scenario: Annotated[
        Path | None,
        typer.Argument(
            help="Scenario TOML file (unless --spec).",
            exists=True,
            dir_okay=False,
        ),
    ] = None,
    robot: Annotated[str | None, typer.Option(help="This process's robot id.")] = None,
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
    # The backends' own options: read by their spelling (`_backend_options`), the driver
    # registry saying whose each one is and which setting it fills.
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
            help="Robot drivers: Unix time of step 0, shared by the fleet (default: now).",
            callback=finite_epoch,
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
    spec: Annotated[Path | None, typer.Option(help=AGENT_SPEC_HELP, allow_dash=True)] = None,
    print_spec: Annotated[
        bool, typer.Option("--print-spec", help="Print the agent's spec (JSON) and exit.")
    ] = False,
) -> None:
    """Run one robot's agent: Zenoh in, behaviour stack, command out. Its options (or
    --spec) make one spec, which the runtime builds the agent from.
    """
    from pydantic import ValidationError

    from phalanx.core.errors import ConfigError, DriverUnavailable
    from phalanx.runtime.process_spec import driver_choice

    try:
        if spec is not None:
            checked = _spec_file(ctx, spec, robot=robot, fleet=fleet)
        else:
            checked = _agent_spec(
                scenario=_given(scenario, "SCENARIO (or --spec)"),
                overrides=tuple(set_ or ()),
                robot_id=_given(robot, "--robot"),
                fleet=fleet,
                clock=_clock(clock),
                transport=_transport(
                    mode, listen, connect, (tls_ca, tls_cert, tls_key), lowlatency=lowlatency
                ),
                driver=driver_choice(
                    driver, options=_backend_options(ctx), settings=_driver_settings(driver_setting)
                ),
                epoch_s=epoch, watchdog_s=watchdog, camera=camera, frame_timeout_s=frame_timeout,
                telemetry=_telemetry_target(recording_id, telemetry_file, telemetry_url),
            )  # fmt: skip
    except DriverUnavailable as exc:  # (its backend's library, needed for its settings)
        typer.echo(str(exc), err=True)
        raise typer.Exit(2) from exc
    except (ConfigError, ValidationError) as exc:
        raise typer.BadParameter(_message(exc)) from exc
    if print_spec:
        typer.echo(checked.model_dump_json(indent=2))
        return
    _run_agent(checked)


def _run_agent(spec: AgentSpec) -> None:
    """Hand the spec to the runtime's factory and say how the agent ended (its exit code
    not 0 for a run that did not finish).
    """
    from phalanx.core.errors import DriverUnavailable
    from phalanx.runtime.agent_process import run_agent

    rid = spec.robot_id
    logging.basicConfig(level=logging.INFO, format=f"%(asctime)s {rid} %(levelname)s %(message)s")
    try:
        report, code = run_agent(spec, stop=_stop_on_signals())
    except DriverUnavailable as exc:
        typer.echo(str(exc), err=True)
        raise typer.Exit(2) from exc
    typer.echo(
        f"{rid}: {report.steps} steps, {report.saturations} saturations, "
        f"{report.dropped_messages} dropped messages"
    )
    if code:  # not a finished run: a supervisor (phalanx host) restarts it to rejoin
        from phalanx.runtime.exits import EXIT_WORLD_LOST, agent_exit_reason

        why = agent_exit_reason(code)
        if code == EXIT_WORLD_LOST:
            why = f"no frame from the world for {spec.frame_timeout_s:g} s"
        typer.echo(f"{rid}: {why} (exit code {code}, not a finished run)", err=True)
        raise typer.Exit(code)


# What `phalanx agent --spec` may be given besides (--robot, --fleet: the spec's own).
_WITH_SPEC = ("spec", "print_spec", "robot", "fleet")


def _spec_file(ctx: typer.Context, path: Path, *, robot: str | None, fleet: str) -> AgentSpec:
    """The spec read from `path` (`-`: standard input), given no option beside it but a
    robot and fleet equal to its own.
    """
    from phalanx.runtime.process_spec import read_spec

    given = [name for name in ctx.params if name not in _WITH_SPEC and _given_here(ctx, name)]
    if given:
        spelled = ", ".join(_spelling(ctx, name) for name in given)
        raise typer.BadParameter(f"the spec says everything: leave out {spelled}")
    checked = read_spec(path)
    if robot is not None and robot != checked.robot_id:
        raise typer.BadParameter(f"--robot {robot}: the spec's robot is {checked.robot_id}")
    if _given_here(ctx, "fleet") and fleet != checked.fleet:
        raise typer.BadParameter(f"--fleet {fleet}: the spec's fleet is {checked.fleet}")
    return checked


def _given_here(ctx: typer.Context, name: str) -> bool:
    """Whether parameter `name` was given (on the command line or by its variable)."""
    from typer._click.core import ParameterSource  # (typer is pinned to 0.29)

    return ctx.get_parameter_source(name) not in (None, ParameterSource.DEFAULT)


def _spelling(ctx: typer.Context, name: str) -> str:
    """How parameter `name` is spelled on the command line (`--set`, SCENARIO)."""
    param = next(p for p in ctx.command.params if p.name == name)
    return param.opts[0] if param.opts[0].startswith("-") else name.upper()


def _agent_spec(**values: object) -> AgentSpec:
    from phalanx.core.config_files import validate_data
    from phalanx.runtime.process_spec import AgentSpec

    return validate_data(AgentSpec, values, source="phalanx agent")


def _given(value: T | None, name: str) -> T:
    if value is None:
        raise typer.BadParameter(f"missing {name}")
    return value


def _backend_options(ctx: typer.Context) -> dict[str, object]:
    """The driver backends' own options (`--arcos-tcp` ...) by their spelling, as given
    (None: not given); the driver registry says whose each one is.
    """
    from phalanx.drivers import BACKENDS

    declared = {option for entry in BACKENDS.values() for option, _ in entry.options}
    found: dict[str, object] = {}
    for param in ctx.command.params:
        for option in set(param.opts) & declared:
            found[option] = ctx.params.get(param.name or "")
    return found


def _message(exc: Exception) -> str:
    """A spec's error in words: pydantic's own (from a model built directly) as
    `field: message`.
    """
    from pydantic import ValidationError

    if not isinstance(exc, ValidationError):
        return str(exc)
    said = []
    for error in exc.errors():
        text = error["msg"].removeprefix("Value error, ")
        where = ".".join(map(str, error["loc"]))
        said.append(f"{where}: {text}" if where else text)
    return "; ".join(said)


def _driver_settings(pairs: list[str] | None) -> dict[str, object]:
    """`KEY=VALUE` pairs, VALUE a TOML value (a bare word is a string, as with --set)."""
    from phalanx.core.config_files import parse_value

    values: dict[str, object] = {}
    for pair in pairs or []:
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
    speed: Annotated[
        float, typer.Option(help="Real-time speed factor.", callback=speed_factor)
    ] = 1.0,
    listen: ListenOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = "router",
    lowlatency: LowLatencyOpt = False,
    tls_ca: TlsCaOpt = None,
    tls_cert: TlsCertOpt = None,
    tls_key: TlsKeyOpt = None,
    set_: SetOpt = None,
    out: Annotated[
        Path | None,
        typer.Option(
            help="Results folder, used as given (default: results/<scenario>-<controller>-world, "
            "or -world-2, -3 ... if that one holds an earlier run)."
        ),
    ] = None,
    recording: Annotated[bool, typer.Option(help="Write a Rerun .rrd.")] = True,
    epoch: Annotated[
        float | None,
        typer.Option(
            help="Real time: Unix time of tick 0, shared with agents.", callback=finite_epoch
        ),
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
    results_line: Annotated[
        bool,
        typer.Option(
            help="End with the results folder's line (`phalanx up` says it itself, once "
            "every process has ended; a launch reads it from the world's output)."
        ),
    ] = True,
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
    from phalanx.runtime.process_spec import telemetry_for
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
    folder = out or fresh_folder(results_name(config.name, config.controller.kind, "world"))
    target = _telemetry_target(recording_id, telemetry_file, telemetry_url)
    with telemetry_for(target, robot_id=None) as telemetry:
        process = WorldProcess(
            config, load_robot(config.robot), options, telemetry=telemetry,
            checkpoint=lambda so_far: write_checkpoint(so_far, folder),
        )  # fmt: skip
        run_log = process.run(_stop_on_signals())
    try:
        complete = _write_world_results(
            process, run_log, folder, recording=recording, figure_format=fmt, dpi=dpi
        )
    except ResultsNotWritten as exc:
        _results_lost(exc)
    if results_line:
        typer.echo(f"results: {folder}")
    if not complete:
        raise typer.Exit(EXIT_INCOMPLETE)


def _telemetry_target(
    recording_id: str | None, path: Path | None, url: str | None
) -> TelemetryTarget:
    from pydantic import ValidationError

    from phalanx.runtime.process_spec import TelemetryTarget

    try:
        return TelemetryTarget(recording_id=recording_id, file=path, url=url)
    except ValidationError as exc:
        raise typer.BadParameter(_message(exc)) from exc


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
