"""`phalanx launch`, `phalanx status`, `phalanx stop`: a fleet across hosts."""

from __future__ import annotations

import re
import sys
import time
from typing import TYPE_CHECKING, Annotated

import typer

from phalanx.cli.commands.host import DeploymentArg, load_or_exit
from phalanx.cli.numbers import seconds
from phalanx.cli.outputs import launch_run_id
from phalanx.cli.tables import MarkdownOpt, show_table

if TYPE_CHECKING:
    from phalanx.cli.progress import Reporter
    from phalanx.hosts.deployment import LoadedDeployment
    from phalanx.hosts.fleet_output import LiveOutput, Output, Row
    from phalanx.hosts.launch import LaunchOptions
    from phalanx.hosts.protocol import LogLine
    from phalanx.runtime.local_fleet import Child
    from phalanx.runtime.signals import Stoppable
    from phalanx.wire.transport import TransportConfig

ConnectOpt = Annotated[
    list[str] | None,
    typer.Option("--connect", help="Join the fabric here instead (Zenoh endpoint, repeatable)."),
]
ViaOpt = Annotated[
    str | None, typer.Option(help="Join through this host's daemon (default: this machine's).")
]
IdentityOpt = Annotated[
    str | None,
    typer.Option(
        help="A secured fleet: who you are, operator.NAME or viewer.NAME in the deployment's "
        "PKI folder, or a path without .crt/.key (default: $PHALANX_IDENTITY, else the "
        "deployment's only operator)."
    ),
]
SetOpt = Annotated[
    list[str] | None,
    typer.Option("--set", help="Override a scenario field for this run, e.g. duration_s=60."),
]


def _transport(
    loaded: LoadedDeployment, via: str | None, connect: list[str] | None, identity: str | None
) -> TransportConfig:
    from phalanx.hosts.wiring import client_identity, client_transport

    tls = client_identity(loaded, identity)
    return client_transport(loaded.spec, via=via, connect=tuple(connect or ()), tls=tls)


def launch(
    deployment: DeploymentArg,
    set_: SetOpt = None,
    run_id: Annotated[
        str | None,
        typer.Option(
            help="Name of this run, and of its results folder on the world's host (default: "
            "<deployment>-<date>-<time>-<4 hex digits>)."
        ),
    ] = None,
    host_wait: Annotated[
        float,
        typer.Option(
            help="Seconds to wait for every host's daemon (with --local, also to connect).",
            callback=seconds,
        ),
    ] = 30.0,
    timeout: Annotated[
        float | None,
        typer.Option(help="Stop the fleet after this many seconds.", callback=seconds),
    ] = None,
    detach: Annotated[
        bool, typer.Option(help="Return once the fleet is up; end it with `phalanx stop`.")
    ] = False,
    table: Annotated[
        bool | None, typer.Option(help="Live status table (default: on a terminal).")
    ] = None,
    logs: Annotated[bool, typer.Option(help="Show the processes' output.")] = True,
    local: Annotated[
        bool, typer.Option(help="Also start the daemons of hosts on 127.x (all on this machine).")
    ] = False,
    via: ViaOpt = None,
    connect: ConnectOpt = None,
    identity: IdentityOpt = None,
    print_acl: Annotated[
        bool, typer.Option(help="Print every host's generated access-control list and exit.")
    ] = False,
    quiet: Annotated[
        bool, typer.Option("--quiet", "-q", help="No progress (time elapsed and left).")
    ] = False,
) -> None:
    """Start a deployment on its hosts, follow it live, stop it on Ctrl-C or at its end.
    The world's progress, with the time left, goes to stderr (in the live table's title
    on a terminal); the run's results folder, on the world's host, is named at the end.
    """
    from phalanx.core.errors import DeploymentError
    from phalanx.hosts.launch import LaunchOptions
    from phalanx.hosts.protocol import OVERRIDE_PATTERN, RUN_ID_PATTERN

    loaded = load_or_exit(deployment)
    if print_acl:
        _print_acl(loaded)
        return
    if loaded.spec.open_warning:
        typer.secho(loaded.spec.open_warning, fg="red", bold=True, err=True)
    run = run_id or launch_run_id(loaded.spec.name)
    _check_pattern(run, RUN_ID_PATTERN, "--run-id")
    for override in set_ or ():
        _check_pattern(override, OVERRIDE_PATTERN, "--set")
    _check_overrides(loaded, set_ or [])
    options = LaunchOptions(
        run_id=run,
        overrides=tuple(set_ or ()),
        host_wait_s=host_wait,
        timeout_s=timeout,
        detach=detach,
    )
    from phalanx.runtime.signals import stop_on_signals

    stop = stop_on_signals()
    daemons = _start_local_daemons(loaded) if local else []
    try:
        transport = _transport(loaded, via, connect, identity)
        if daemons:  # just started: the fabric is up once one of them is (--host-wait)
            transport = transport.model_copy(update={"open_timeout_s": host_wait})
        code = _run(loaded, options, transport, (table, logs, quiet), stop)
    except DeploymentError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    finally:
        _stop_local_daemons(daemons)
    raise typer.Exit(code)


def _print_acl(loaded: LoadedDeployment) -> None:
    from phalanx.hosts.access import describe_acls

    if not loaded.spec.secured:
        typer.echo(
            f"# deployment {loaded.spec.name!r} is not secured (mode 'open'"
            + (", implied: every host is on loopback" if loaded.spec.security is None else "")
            + "): no access control; everyone may do everything"
        )
        return
    typer.echo(describe_acls(loaded.spec))


def _check_pattern(value: str, pattern: str, what: str) -> None:
    import re

    if not re.match(pattern, value):
        raise typer.BadParameter(f"{what} {value!r} does not match {pattern}")


def _check_overrides(loaded: LoadedDeployment, overrides: list[str]) -> None:
    from phalanx.core.config_files import apply_overrides
    from phalanx.core.errors import ConfigError

    if overrides:
        try:
            apply_overrides(loaded.scenario, overrides, source=str(loaded.scenario_path))
        except ConfigError as exc:
            raise typer.BadParameter(str(exc)) from exc


def _run(
    loaded: LoadedDeployment,
    options: LaunchOptions,
    transport: TransportConfig,
    shown: tuple[bool | None, bool, bool],
    stop: Stoppable,
) -> int:
    """Launch with the output asked for: `shown` is (the live table, the processes'
    output, quiet).
    """
    from phalanx.cli.progress import Reporter
    from phalanx.core.config_files import apply_overrides
    from phalanx.hosts.fleet_output import LiveOutput, PlainOutput
    from phalanx.hosts.launch import launch

    table, logs, quiet = shown
    scenario = apply_overrides(loaded.scenario, list(options.overrides))
    rate_hz = scenario.control_rate_hz
    title = f"{loaded.spec.name} · fleet {loaded.spec.fleet} · run {options.run_id}"
    if table if table is not None else sys.stdout.isatty():
        with LiveOutput(title, logs=logs) as live:
            line = TitleLine(live, title)
            reporter = Reporter(
                "launch", unit="s of run", stream=line, quiet=quiet, tty=True, from_first=True
            )
            watched = WorldProgress(live, reporter, rate_hz)
            return launch(loaded, options, transport=transport, output=watched, stop=stop)
    reporter = Reporter("launch", unit="s of run", quiet=quiet, from_first=True)

    def write(text: str) -> None:
        reporter.close()  # (a terminal's progress line ended before a line of output)
        typer.echo(text)

    output = WorldProgress(PlainOutput(write, logs=logs), reporter, rate_hz)
    output.event(f"launching {title}")
    try:
        return launch(loaded, options, transport=transport, output=output, stop=stop)
    finally:
        reporter.close()


_TICKS = re.compile(r"^tick (\d{1,12})/(\d{1,12})$")


class WorldProgress:
    """A launcher's output (`phalanx.hosts.fleet_output.Output`) passed on as it is, the
    world's progress (its row's `tick k/n`) reported on the way, in seconds of run.
    """

    def __init__(self, inner: Output, reporter: Reporter, rate_hz: float) -> None:
        self.inner, self.reporter, self.rate_hz = inner, reporter, rate_hz
        self.total_s: float | None = None  # the run's length, once the world said it

    def event(self, text: str) -> None:
        """Pass an event on."""
        self.inner.event(text)

    def log(self, line: LogLine) -> None:
        """Pass a child's line on."""
        self.inner.log(line)

    def update(self, rows: list[Row]) -> None:
        """Pass the rows on, and report the world's ticks."""
        self.inner.update(rows)
        for row in (r for r in rows if r.name == "world"):
            ticks = _TICKS.match(row.state)
            if ticks is not None:
                done, self.total_s = (int(n) / self.rate_hz for n in ticks.groups())
                self.reporter(done, self.total_s)
            elif row.process == "finished" and self.total_s is not None:
                self.reporter(self.total_s, self.total_s)


class TitleLine:
    """Where a terminal's progress line goes while the live table is shown: the table's
    title, beside its own (the table owns the screen; a line of its own would tear it).
    """

    def __init__(self, live: LiveOutput, title: str) -> None:
        self.live, self.title = live, title

    def write(self, text: str, /) -> int:
        """Show the line `text` carries in the title."""
        said = text.strip("\r\n ")
        if said:
            self.live.title = f"{self.title} · {said}"
        return len(text)

    def flush(self) -> None:
        """Nothing to push: the table redraws its title."""

    def isatty(self) -> bool:
        """In place, as in a terminal."""
        return True


def _start_local_daemons(loaded: LoadedDeployment) -> list[Child]:
    from phalanx.hosts.wiring import loopback_hosts
    from phalanx.runtime.local_fleet import Child

    daemons = []
    for name in loopback_hosts(loaded.spec):
        argv = [sys.executable, "-m", "phalanx", "host", str(loaded.path), "--name", name]
        child = Child(f"host-{name}", [*argv, "--quiet"])
        child.start()
        daemons.append(child)
    return daemons


def _stop_local_daemons(daemons: list[Child]) -> None:
    from phalanx.runtime.local_fleet import stop_all

    stop_all(daemons)


def status(
    deployment: DeploymentArg,
    json_: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False,
    markdown: MarkdownOpt = False,
    listen_s: Annotated[
        float,
        typer.Option(
            "--listen-s", help="Seconds to listen to the robots' states.", callback=seconds
        ),
    ] = 1.5,
    via: ViaOpt = None,
    connect: ConnectOpt = None,
    identity: IdentityOpt = None,
) -> None:
    """Show a running fleet: every host's processes and every robot's state."""
    from phalanx.core.errors import DeploymentError
    from phalanx.hosts.fleet_client import FleetClient
    from phalanx.hosts.fleet_output import fleet_rows, status_document

    loaded = load_or_exit(deployment)
    try:
        with FleetClient(loaded, _transport(loaded, via, connect, identity)) as client:
            time.sleep(listen_s)
            statuses = client.statuses()
            skews = client.clock_skews()
            processes = client.process_statuses()
            rows = fleet_rows(
                loaded, statuses, client.watch, world=processes.get("world"), processes=processes
            )
    except DeploymentError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    missing = [h for h, s in statuses.items() if s is None]
    if json_:
        typer.echo(status_document(statuses, rows, skews))
    else:
        title = f"{loaded.spec.name} · fleet {loaded.spec.fleet}"
        show_table(STATUS_HEADERS, status_cells(rows), title=title, markdown=markdown)
        for host_name, s in statuses.items():
            line = f"host {host_name}: " + (
                f"run {s.run_id or '-'}, {s.requests} requests, {s.refused} refused, "
                f"clock {skews.get(host_name, 0.0) * 1e3:+.0f} ms"
                if s is not None
                else "not present"
            )
            typer.echo(line)
    raise typer.Exit(1 if missing else 0)


STATUS_HEADERS = ("robot", "host", "process", "restarts", "state", "leader", "rate", "dropped",
                  "relinks", "last error")  # fmt: skip


def status_cells(rows: list[Row]) -> list[list[str]]:
    """The cells of `phalanx status`'s table, a row per robot and one for the world."""
    return [
        [
            row.name, row.host, row.process, str(row.restarts), row.state, row.leader,
            f"{row.rate_hz:.1f} Hz" if row.rate_hz is not None else "-",
            "-" if row.dropped is None else str(row.dropped),
            "-" if row.relinks is None else str(row.relinks),
            row.last_error[-80:] or "-",
        ]
        for row in rows
    ]  # fmt: skip


def stop(
    deployment: DeploymentArg,
    run_id: Annotated[
        str | None, typer.Option(help="Only if this run is the hosts' current one.")
    ] = None,
    via: ViaOpt = None,
    connect: ConnectOpt = None,
    wait: Annotated[
        float, typer.Option(help="Seconds to wait for every process to end.", callback=seconds)
    ] = 15.0,
    host_wait: Annotated[
        float, typer.Option(help="Seconds to wait for the hosts.", callback=seconds)
    ] = 2.0,
    identity: IdentityOpt = None,
) -> None:
    """Stop a running fleet on every host (SIGTERM, then SIGKILL after a grace period)."""
    from phalanx.core.errors import DeploymentError
    from phalanx.hosts.fleet_client import FleetClient

    loaded = load_or_exit(deployment)
    try:
        with FleetClient(loaded, _transport(loaded, via, connect, identity)) as client:
            deadline = time.monotonic() + host_wait
            while time.monotonic() < deadline and client.watch.present() != set(client.host_names):
                time.sleep(0.1)
            replies = client.stop(run_id)
            left = client.wait_stopped(wait)
    except DeploymentError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    absent = [h for h in loaded.spec.hosts if h.name not in replies]
    for host_name, reply in replies.items():
        verdict = "no answer" if reply is None else ("stopping" if reply.ok else reply.error)
        typer.echo(f"host {host_name}: {verdict}")
    for entry in absent:
        typer.echo(f"host {entry.name}: not present")
    if left:
        typer.echo(f"still running: {', '.join(left)}", err=True)
    failed = left or absent or any(r is None or not r.ok for r in replies.values())
    raise typer.Exit(1 if failed else 0)


def register(app: typer.Typer) -> None:
    """Add `phalanx launch`, `phalanx status` and `phalanx stop`."""
    app.command("launch")(launch)
    app.command("status")(status)
    app.command("stop")(stop)
