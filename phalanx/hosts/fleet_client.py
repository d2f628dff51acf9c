"""`phalanx launch`, `status` and `stop`: a deployed fleet, driven through its hosts' daemons.

The launcher is a Zenoh client of one host's daemon (this machine's, if it is one of the
hosts; else the router, or the first host it reaches). It waits (bounded) for every host
of the deployment to be present and to hold the same deployment and scenario files,
asks each host to spawn its part of the run, then follows the run: the hosts' status
queryables (process states, restarts, last errors), the robots' own state messages
(behaviour state, leader, publication rate) and the children's output (log lines the
daemons publish). It ends when every process has ended, on its timeout, or on Ctrl-C,
and then asks every host to stop what is left.
"""

from __future__ import annotations

import contextlib
import json
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

from pydantic import ValidationError

from phalanx.core.config import Scenario, apply_overrides
from phalanx.core.errors import DeploymentError, TransportError
from phalanx.core.lifecycle import Closing
from phalanx.hosts.deployment import LoadedDeployment, client_transport, needs_epoch
from phalanx.hosts.protocol import (
    ACTIVE_STATES,
    ChildStatus,
    HostReply,
    HostStatus,
    LogLine,
    SpawnRequest,
    StopRequest,
)
from phalanx.runtime.signals import Stoppable
from phalanx.wire.keys import host_key, host_of, hosts_key, logs_key, robots_key, status_key
from phalanx.wire.messages import RobotState
from phalanx.wire.transport import FleetSession, TransportConfig, open_session

RATE_WINDOW_S = 2.0
POLL_S = 0.5
ASK_TIMEOUT_S = 1.5


@dataclass
class LaunchOptions:
    """What `phalanx launch` does beyond the deployment file."""

    run_id: str
    overrides: tuple[str, ...] = ()
    host_wait_s: float = 30.0
    timeout_s: float | None = None  # default: the scenario's duration plus a margin
    detach: bool = False  # return once the fleet is up; `phalanx stop` ends it
    finish_grace_s: float = 15.0  # agents still running this long after the world ended


@dataclass(frozen=True)
class Row:
    """One line of the status table."""

    name: str
    host: str
    process: str
    restarts: int
    state: str
    leader: str
    rate_hz: float | None
    last_error: str


class Output(Protocol):
    """Where a launcher shows what happens (a live table, or plain lines)."""

    def event(self, text: str) -> None:
        """Something worth a line of its own."""

    def log(self, line: LogLine) -> None:
        """A child's output line."""

    def update(self, rows: list[Row]) -> None:
        """The fleet now."""


class FleetWatch:
    """Robot states and log lines as they arrive (Zenoh callbacks fill it, the loop reads)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.states: dict[str, RobotState] = {}
        self.first_seen: dict[str, float] = {}
        self._arrivals: dict[str, deque[float]] = {}
        self.logs: queue.SimpleQueue[LogLine] = queue.SimpleQueue()
        self.hosts_present: set[str] = set()
        self.malformed_logs = 0

    def on_state(self, _key: str, state: RobotState) -> None:
        """A robot's state (callback side)."""
        now = time.monotonic()
        with self._lock:
            self.states[state.robot_id] = state
            self.first_seen.setdefault(state.robot_id, now)
            arrivals = self._arrivals.setdefault(state.robot_id, deque(maxlen=200))
            arrivals.append(now)

    def on_log(self, sample: Any) -> None:
        """A child's output line (callback side); malformed ones are counted."""
        try:
            self.logs.put(LogLine.model_validate_json(sample.payload.to_bytes()))
        except ValidationError:
            self.malformed_logs += 1

    def on_host(self, key: str, alive: bool) -> None:
        """A host daemon's token appeared or vanished (callback side)."""
        with self._lock:
            (self.hosts_present.add if alive else self.hosts_present.discard)(host_of(key))

    def present(self) -> set[str]:
        """The hosts whose daemon is on the fabric now."""
        with self._lock:
            return set(self.hosts_present)

    def rate_hz(self, robot_id: str, now: float) -> float | None:
        """States per second from `robot_id` over the last RATE_WINDOW_S."""
        with self._lock:
            arrivals = [t for t in self._arrivals.get(robot_id, ()) if now - t <= RATE_WINDOW_S]
        return len(arrivals) / RATE_WINDOW_S if arrivals else None

    def state(self, robot_id: str) -> RobotState | None:
        """The last state of `robot_id`."""
        with self._lock:
            return self.states.get(robot_id)

    def seen_since(self, robot_ids: list[str], since: float) -> bool:
        """Whether every robot has published a state since `since` (monotonic)."""
        with self._lock:
            return all(self.first_seen.get(r, -1.0) >= since for r in robot_ids)


class FleetClient(Closing):
    """A client session on a deployment's fabric; asks its hosts; context manager."""

    def __init__(self, loaded: LoadedDeployment, transport: TransportConfig) -> None:
        self.loaded, self.spec = loaded, loaded.spec
        try:
            self.session: FleetSession = open_session(transport)
        except TransportError as exc:
            raise DeploymentError(
                f"cannot reach the fabric of deployment {self.spec.name!r} at "
                f"{', '.join(transport.connect)}: is `phalanx host` (or `phalanx router`) "
                "running there?"
            ) from exc
        self.watch = FleetWatch()
        try:
            self._wire(self.spec.fleet)
        except BaseException:
            self.session.close()
            raise

    def _wire(self, fleet: str) -> None:
        self.session.watch_alive(hosts_key(fleet, "alive"), self.watch.on_host)
        self.session.subscribe(robots_key(fleet, "state"), RobotState, self.watch.on_state)
        self.session.hold(self.session.zenoh.declare_subscriber(logs_key(fleet), self.watch.on_log))

    @property
    def host_names(self) -> list[str]:
        """Every host of the deployment, in file order."""
        return [h.name for h in self.spec.hosts]

    def ask(
        self, topic: str, payloads: dict[str, bytes], timeout_s: float = ASK_TIMEOUT_S
    ) -> dict[str, HostReply | None]:
        """Send each host its payload on `topic` at once; each reply (None: no answer)."""
        fleet = self.spec.fleet
        pending = {
            host: self.session.zenoh.get(
                host_key(fleet, host, topic), payload=payload, timeout=timeout_s
            )
            for host, payload in payloads.items()
        }
        return {host: _first_reply(replies) for host, replies in pending.items()}

    def statuses(self, hosts: list[str] | None = None) -> dict[str, HostStatus | None]:
        """Each host's status (None: it did not answer)."""
        replies = self.ask("status", dict.fromkeys(hosts or self.host_names, b""))
        return {h: r.status if r is not None else None for h, r in replies.items()}

    def world_status(self) -> dict[str, Any] | None:
        """The world's own status (tick, missed deadlines), if it answers."""
        replies = self.session.query_status(status_key(self.spec.fleet, "world"), 0.5)
        return replies[0] if replies else None

    def wait_for_hosts(self, timeout_s: float, say: Callable[[str], None]) -> dict[str, HostStatus]:
        """Every host's status once all are present; DeploymentError naming the missing."""
        deadline = time.monotonic() + timeout_s
        statuses: dict[str, HostStatus | None] = {}
        while True:
            missing = [h for h in self.host_names if h not in self.watch.present()]
            if not missing:
                statuses = self.statuses()
                missing = [h for h, s in statuses.items() if s is None]
            if not missing:
                break
            if time.monotonic() > deadline:
                raise DeploymentError(self._missing_message(missing, timeout_s))
            time.sleep(0.1)
        present = {h: s for h, s in statuses.items() if s is not None}
        self._check_digests(present)
        self._check_clocks(say)
        return present

    def _missing_message(self, missing: list[str], timeout_s: float) -> str:
        path = self.loaded.path
        return (
            f"hosts not present after {timeout_s:.0f} s: {', '.join(missing)}. "
            f"On each, run `phalanx host {path} --name NAME` "
            f"(reached through {', '.join(self.session_connect())})"
        )

    def session_connect(self) -> tuple[str, ...]:
        """Where this client connected (for messages)."""
        return client_transport(self.spec).connect

    def _check_digests(self, statuses: dict[str, HostStatus]) -> None:
        wrong = [
            host
            for host, status in statuses.items()
            if status.digest != self.loaded.digest or status.deployment != self.spec.name
        ]
        if wrong:
            raise DeploymentError(
                f"hosts {', '.join(wrong)} hold a different {self.loaded.path.name} or scenario "
                f"(digest {self.loaded.digest[:12]} here): copy the same files to every host "
                "and restart their daemons"
            )

    def _check_clocks(self, say: Callable[[str], None]) -> None:
        for host, skew_s in self.clock_skews().items():
            if abs(skew_s) > self.spec.max_clock_skew_s:
                say(
                    f"warning: host {host}'s clock is {skew_s * 1e3:+.0f} ms from this one's "
                    f"(more than {self.spec.max_clock_skew_s * 1e3:.0f} ms): robots on real "
                    "drivers share an epoch; sync the clocks (chrony)"
                )

    def clock_skews(self) -> dict[str, float]:
        """Each host's clock minus this one's, s (half the round trip is the error bound)."""
        sent = time.time()
        statuses = self.statuses()
        received = time.time()
        middle = (sent + received) / 2.0
        return {h: s.time_unix - middle for h, s in statuses.items() if s is not None}

    def spawn(
        self, run_id: str, *, overrides: tuple[str, ...], epoch_unix: float | None
    ) -> dict[str, HostStatus]:
        """Ask every host with work to start its part; DeploymentError listing refusals."""
        request = SpawnRequest(
            deployment=self.spec.name,
            digest=self.loaded.digest,
            run_id=run_id,
            epoch_unix=epoch_unix,
            overrides=overrides,
        )
        payload = request.model_dump_json().encode("utf-8")
        busy = [h for h in self.host_names if self.spec.robots_on(h) or self.spec.runs_world(h)]
        replies = self.ask("spawn", dict.fromkeys(busy, payload), timeout_s=5.0)
        problems = [
            f"host {h}: {r.error if r is not None else 'no answer'}"
            for h, r in replies.items()
            if r is None or not r.ok
        ]
        if problems:
            raise DeploymentError("the fleet could not start:\n  " + "\n  ".join(problems))
        return {h: r.status for h, r in replies.items() if r is not None}

    def stop(self, run_id: str | None = None) -> dict[str, HostReply | None]:
        """Ask every present host to stop its processes (of `run_id`, if given)."""
        request = StopRequest(deployment=self.spec.name, run_id=run_id)
        payload = request.model_dump_json().encode("utf-8")
        present = [h for h in self.host_names if h in self.watch.present()]
        return self.ask("stop", dict.fromkeys(present, payload))

    def wait_stopped(self, timeout_s: float) -> list[str]:
        """Wait (bounded) until no present host has an active child; the ones left."""
        deadline = time.monotonic() + timeout_s
        while True:
            present = [h for h in self.host_names if h in self.watch.present()]
            statuses = self.statuses(present) if present else {}
            left = [
                f"{h}/{c.name}"
                for h, s in statuses.items()
                if s is not None
                for c in s.children
                if c.state in ACTIVE_STATES
            ]
            if not left or time.monotonic() > deadline:
                return left
            time.sleep(0.2)

    def close(self) -> None:
        """Close the session; safe twice."""
        self.session.close()


def _first_reply(replies: Any) -> HostReply | None:
    for reply in replies:
        if reply.ok is not None:
            with contextlib.suppress(ValidationError):
                return HostReply.model_validate_json(reply.ok.payload.to_bytes())
    return None


# --- the table ----------------------------------------------------------------------------


def fleet_rows(
    loaded: LoadedDeployment,
    statuses: dict[str, HostStatus | None],
    watch: FleetWatch,
    *,
    world: dict[str, Any] | None = None,
    total_ticks: int | None = None,
) -> list[Row]:
    """The status table: one row per robot, and the world (`tick k/total_ticks`)."""
    now = time.monotonic()
    present = watch.present()
    rows = []
    for placement in loaded.spec.robots:
        child = _child(statuses, placement.host, placement.id)
        state = watch.state(placement.id)
        rows.append(
            Row(
                name=placement.id,
                host=placement.host,
                process=_process(child, placement.host in present),
                restarts=child.restarts if child else 0,
                state=state.fsm_state if state else "-",
                leader=(state.leader_id or "-") if state else "-",
                rate_hz=watch.rate_hz(placement.id, now),
                last_error=child.last_error if child else "",
            )
        )
    if loaded.spec.world is not None:
        host = loaded.spec.world.host
        child = _child(statuses, host, "world")
        process = _process(child, host in present)
        error = child.last_error if child else ""
        progress = _world_state(world, total_ticks or _ticks(loaded.scenario))
        rows.append(Row("world", host, process, 0, progress, "-", None, error))
    return rows


def _ticks(scenario: Scenario) -> int:
    return round(scenario.duration_s * scenario.control_rate_hz)


def _world_state(world: dict[str, Any] | None, total_ticks: int) -> str:
    if not world or "tick" not in world:
        return "-"
    return f"tick {world['tick']}/{total_ticks}"


def _child(statuses: dict[str, HostStatus | None], host: str, name: str) -> ChildStatus | None:
    status = statuses.get(host)
    if status is None:
        return None
    return next((c for c in status.children if c.name == name), None)


def _process(child: ChildStatus | None, host_present: bool) -> str:
    if not host_present:
        return "host lost"
    return child.state if child is not None else "-"


def rows_as_json(rows: list[Row]) -> list[dict[str, Any]]:
    """The table as plain data."""
    return [row.__dict__ for row in rows]


# --- the launch -------------------------------------------------------------------------


@dataclass
class _Run:
    started: float
    spawned: float = 0.0
    up_at: float | None = None
    world_done_at: float | None = None
    statuses: dict[str, HostStatus | None] = field(default_factory=dict)
    results: list[str] = field(default_factory=list)


def launch(
    loaded: LoadedDeployment,
    options: LaunchOptions,
    *,
    transport: TransportConfig,
    output: Output,
    stop: Stoppable,
) -> int:
    """Run a deployment to its end (or Ctrl-C, or the timeout); the exit code."""
    run = _Run(started=time.monotonic())
    with FleetClient(loaded, transport) as client:
        client.wait_for_hosts(options.host_wait_s, output.event)
        output.event(
            f"hosts present: {', '.join(client.host_names)} "
            f"({time.monotonic() - run.started:.2f} s)"
        )
        epoch = time.time() + loaded.spec.startup_s if needs_epoch(loaded) else None
        try:
            run.statuses = dict(
                client.spawn(options.run_id, overrides=options.overrides, epoch_unix=epoch)
            )
            run.spawned = time.monotonic()
            output.event(f"run {options.run_id} started ({run.spawned - run.started:.2f} s)")
            code = _follow(client, loaded, options, run, output, stop)
        except BaseException:  # whatever started must not outlive a failed launch
            _stop_everything(client, options, output)
            raise
        if not options.detach or code != 0:
            _stop_everything(client, options, output)
            _drain_logs(client.watch, output, run)
        for line in run.results:
            output.event(line)
    return code


def _follow(
    client: FleetClient,
    loaded: LoadedDeployment,
    options: LaunchOptions,
    run: _Run,
    output: Output,
    stop: Stoppable,
) -> int:
    timeout_s = options.timeout_s or _default_timeout_s(loaded)
    deadline = run.started + timeout_s
    robots = [r.id for r in loaded.spec.robots]
    ticks = _ticks(apply_overrides(loaded.scenario, list(options.overrides)))
    while not stop.wait(POLL_S):
        _drain_logs(client.watch, output, run)
        run.statuses.update(client.statuses())
        world = client.world_status()
        rows = fleet_rows(loaded, run.statuses, client.watch, world=world, total_ticks=ticks)
        output.update(rows)
        if run.up_at is None and client.watch.seen_since(robots, run.spawned):
            run.up_at = time.monotonic()
            output.event(f"fleet up in {run.up_at - run.started:.2f} s (every robot publishing)")
            if options.detach:
                return 0
        code = _finished(run, loaded, options)
        if code is not None:
            return code
        if time.monotonic() > deadline:
            output.event(f"timed out after {timeout_s:.0f} s")
            return 1
    output.event("interrupted")
    return 1


def _default_timeout_s(loaded: LoadedDeployment) -> float:
    speed = loaded.spec.world.speed if loaded.spec.world else 1.0
    return loaded.scenario.duration_s / speed + loaded.spec.startup_s + 120.0


def _finished(run: _Run, loaded: LoadedDeployment, options: LaunchOptions) -> int | None:
    children = [c for s in run.statuses.values() if s is not None for c in s.children]
    if any(c.state == "failed" for c in children if c.kind == "world"):
        return 1
    world = [c for c in children if c.kind == "world"]
    if world and world[0].state in ("finished", "stopped"):
        run.world_done_at = run.world_done_at or time.monotonic()
        late = time.monotonic() - run.world_done_at > options.finish_grace_s
        if late or not any(c.state in ACTIVE_STATES for c in children):
            return 0 if world[0].state == "finished" else 1
        return None
    if loaded.spec.world is not None or not children:
        return None
    if any(c.state in ACTIVE_STATES for c in children):
        return None
    return 1 if any(c.state == "failed" for c in children) else 0


def _stop_everything(client: FleetClient, options: LaunchOptions, output: Output) -> None:
    replies = client.stop(options.run_id)
    for host, reply in replies.items():
        if reply is None:
            output.event(f"host {host} did not answer the stop request")
    left = client.wait_stopped(timeout_s=15.0)
    if left:
        output.event(f"still running after the stop request: {', '.join(left)}")


def _drain_logs(watch: FleetWatch, output: Output, run: _Run) -> None:
    while True:
        try:
            line = watch.logs.get_nowait()
        except queue.Empty:
            return
        if line.child == "world" and line.line.startswith("results: "):
            folder = line.line.removeprefix("results: ")
            run.results.append(f"results on host {line.host}: {folder}")
        output.log(line)


# --- outputs ------------------------------------------------------------------------------


class PlainOutput:
    """Lines: events, log lines, every change of a row, the world's progress now and then."""

    def __init__(
        self, write: Callable[[str], None], *, logs: bool = True, progress_s: float = 10.0
    ) -> None:
        self.write = write
        self.logs = logs
        self.progress_s = progress_s
        self._last: dict[str, tuple[str, str, str]] = {}
        self._progress_at = time.monotonic()

    def event(self, text: str) -> None:
        """Print an event."""
        self.write(f"{_clock()} {text}")

    def log(self, line: LogLine) -> None:
        """Print a child's line, prefixed with host/child."""
        if self.logs:
            self.write(f"{_clock()} [{line.host}/{line.child}] {line.line}")

    def update(self, rows: list[Row]) -> None:
        """Print the rows that changed."""
        now = time.monotonic()
        for row in rows:
            ticking = row.name == "world" and row.state.startswith("tick ")
            key = (row.process, "tick" if ticking else row.state, row.leader)
            if ticking and now - self._progress_at > self.progress_s:
                self._progress_at = now
                self.write(f"{_clock()} world on {row.host}: {row.state}")
            if self._last.get(row.name) != key:
                self._last[row.name] = key
                leader = f" (leader {row.leader})" if row.leader != "-" else ""
                self.write(
                    f"{_clock()} {row.name} on {row.host}: {row.process}, {row.state}{leader}"
                )


def _clock() -> str:
    return time.strftime("%H:%M:%S")


def render_table(rows: list[Row], *, title: str) -> Any:
    """A rich Table of the rows."""
    from rich.table import Table

    table = Table(title=title, expand=False)
    for column in ("robot", "host", "process", "restarts", "state", "leader", "rate", "last error"):
        table.add_column(column, no_wrap=column != "last error", overflow="fold")
    for row in rows:
        rate = f"{row.rate_hz:.1f} Hz" if row.rate_hz is not None else "-"
        table.add_row(
            row.name,
            row.host,
            _styled(row.process),
            str(row.restarts),
            row.state,
            row.leader,
            rate,
            row.last_error[-80:],
        )
    return table


def _styled(process: str) -> str:
    colour = {"running": "green", "failed": "red", "host lost": "red", "backoff": "yellow"}
    return f"[{colour[process]}]{process}[/]" if process in colour else process


class LiveOutput(Closing):
    """A live rich table; events and log lines scroll above it. Context manager."""

    def __init__(self, title: str, *, logs: bool = True) -> None:
        from rich.console import Console
        from rich.live import Live

        self.title = title
        self.logs = logs
        self.console = Console()
        self.live = Live(render_table([], title=title), console=self.console, refresh_per_second=4)
        self.live.start()

    def event(self, text: str) -> None:
        """Print an event above the table."""
        self.console.print(f"{_clock()} {text}", markup=False, highlight=False)

    def log(self, line: LogLine) -> None:
        """Print a child's line above the table."""
        if self.logs:
            style = {"error": "red", "warning": "yellow"}.get(line.level)
            self.console.print(
                f"[{line.host}/{line.child}] {line.line}",
                style=style,
                markup=False,
                highlight=False,
            )

    def update(self, rows: list[Row]) -> None:
        """Redraw the table."""
        self.live.update(render_table(rows, title=self.title))

    def close(self) -> None:
        """Stop redrawing; safe twice."""
        self.live.stop()


def status_document(
    statuses: dict[str, HostStatus | None], rows: list[Row], skews: dict[str, float]
) -> str:
    """`phalanx status --json`: hosts (None if absent), robots, clock skews."""
    hosts = {h: (s.model_dump() if s is not None else None) for h, s in statuses.items()}
    return json.dumps(
        {"hosts": hosts, "robots": rows_as_json(rows), "clock_skew_s": skews}, indent=2
    )
