"""`phalanx host`: the per-host daemon that starts and supervises a fleet's processes.

The daemon is its host's Zenoh router (endpoints from the deployment file), holds a
liveliness token `phalanx/<fleet>/host/<name>/alive`, and answers spawn, stop and status
requests on its queryables (see `phalanx.hosts.protocol`). It starts only what its own
copy of the deployment assigns to its host: the agents of those robots and, if the world
runs here, the world; on the host the deployment's `[ros2]` names, the ROS 2 bridge,
with the world. What each runs is built from the deployment alone (an agent's spec,
handed on its standard input; the world's and the bridge's command lines); a request
names the deployment and carries a run id, an epoch and scenario overrides, all checked first
(`phalanx.hosts.request_checks`). A malformed or refused request is answered with the
reason and counted; it never ends the daemon. A secured daemon remembers the signed
requests it served in its state folder (`default_state_dir`), so that one sent again is
refused after a restart too (`phalanx.hosts.request_auth`).

Children (`phalanx.hosts.children`) run in their own session (process group), with their
output piped: every line is kept (last error, shown by `status`), echoed to the daemon's
log, and published on `phalanx/<fleet>/host/<name>/log/<child>`. A crashed agent is
restarted with exponential back-off; a crashed world is not (a new world would restart
the scenario). On SIGINT or SIGTERM every child gets SIGTERM, then SIGKILL after a grace
period, and the session is closed. (If the daemon itself is killed, systemd's control
group takes the children down; and a robot whose liveliness token is still up is never
started a second time.)
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from pydantic import ValidationError

from phalanx.core.errors import PhalanxError, RequestRefused
from phalanx.hosts.access import bridge_host, ca_path, security_of
from phalanx.hosts.children import LogLevel, ManagedChild, backoff_delay_s, exit_reason
from phalanx.hosts.deployment import LoadedDeployment
from phalanx.hosts.protocol import (
    MAX_REQUEST_BYTES,
    HostReply,
    HostStatus,
    LogLine,
    SpawnRequest,
    StopRequest,
)
from phalanx.hosts.request_auth import RequestVerifier
from phalanx.hosts.request_checks import RequestChecks, validation_summary
from phalanx.hosts.wiring import (
    RunParameters,
    agent_spec,
    bridge_argv,
    secured_host_transport,
    world_argv,
)
from phalanx.runtime.exits import EXIT_INCOMPLETE
from phalanx.runtime.local_fleet import GRACE_S
from phalanx.runtime.process_spec import AgentSpec, spawn_argv
from phalanx.runtime.signals import Stoppable
from phalanx.wire.keys import alive_pattern, host_key, log_key
from phalanx.wire.transport import FleetSession, TransportConfig, open_session

log = logging.getLogger("phalanx.host")
child_log = logging.getLogger("phalanx.host.child")
TOPICS = ("spawn", "stop", "status")
BRIDGE = "ros2-bridge"  # the ROS 2 bridge's child (started and stopped with the world)


@dataclass
class DaemonOptions:
    """How a host daemon runs its children."""

    python: str = sys.executable
    workdir: Path = field(default_factory=Path.cwd)
    echo: bool = True  # copy children's output to the daemon's log
    grace_s: float = GRACE_S
    tick_s: float = 0.05
    state_dir: Path | None = None  # what must outlive the daemon; None: default_state_dir


def default_state_dir(fleet: str, host: str) -> Path:
    """Where a host's daemon keeps what must survive a restart (the requests it served):
    `phalanx/<fleet>/<host>` under systemd's `StateDirectory=` (`$STATE_DIRECTORY`), else
    under `$XDG_STATE_HOME`, else under `~/.local/state`.
    """
    systemd = os.environ.get("STATE_DIRECTORY", "").split(":")[0]
    xdg = os.environ.get("XDG_STATE_HOME", "")
    base = Path(systemd or xdg or Path.home() / ".local" / "state")
    return base / "phalanx" / fleet / host


class HostDaemon:
    """Serves one host of one deployment: requests in, supervised processes out."""

    def __init__(
        self, loaded: LoadedDeployment, name: str, options: DaemonOptions | None = None
    ) -> None:
        loaded.spec.host(name)  # ConfigError naming the hosts if `name` is not one
        self.loaded, self.name = loaded, name
        self.spec = loaded.spec
        self.options = options or DaemonOptions()
        self.checks = RequestChecks(loaded, name)
        self.verifier = _verifier(loaded, name, self.options) if self.spec.secured else None
        self.children: dict[str, ManagedChild] = {}
        self.run_id: str | None = None
        self.requests = 0
        self.refused = 0
        self.started = time.monotonic()
        self._alive: set[str] = set()
        self._lock = threading.Lock()
        self._queryables: dict[str, Any] = {}
        self._publishers: dict[str, Any] = {}
        self._session: FleetSession | None = None

    # --- the loop -----------------------------------------------------------------------

    def run(self, stop: Stoppable) -> None:
        """Serve until `stop` is set; then stop every child and close the session."""
        transport = secured_host_transport(self.loaded, self.name)
        if self.spec.open_warning:
            log.warning("%s", self.spec.open_warning)
        with open_session(transport) as session:
            self._session = session
            self._wire(session)
            self._announce(transport)
            try:
                while not stop.is_set():
                    self.serve_requests()
                    self.supervise()
                    stop.wait(self.options.tick_s)
            finally:
                self.shutdown()

    def _announce(self, transport: TransportConfig) -> None:
        robots = ", ".join(self.spec.robots_on(self.name)) or "none"
        world = "; the world runs here" if self.spec.runs_world(self.name) else ""
        log.info(
            "host %s of fleet %s (deployment %s): listening on %s, connecting to %s; "
            "robots here: %s%s",
            self.name, self.spec.fleet, self.spec.name, ", ".join(transport.listen),
            ", ".join(transport.connect) or "nobody (others connect here)", robots, world,
        )  # fmt: skip

    def _wire(self, session: FleetSession) -> None:
        import zenoh

        fleet = self.spec.fleet
        session.declare_alive(host_key(fleet, self.name, "alive"))
        session.watch_alive(alive_pattern(fleet), self._on_alive)
        for topic in TOPICS:
            key = host_key(fleet, self.name, topic)
            queryable = session.zenoh.declare_queryable(key, zenoh.handlers.RingChannel(64))
            self._queryables[topic] = session.hold(queryable)

    def _on_alive(self, key: str, alive: bool) -> None:
        name = key.rsplit("/", 1)[-1]
        with self._lock:
            (self._alive.add if alive else self._alive.discard)(name)

    def serve_requests(self) -> None:
        """Answer every request waiting on the queryables."""
        for topic, queryable in self._queryables.items():
            while (query := queryable.try_recv()) is not None:
                with query:
                    reply = self.answer(topic, _payload(query))
                    with contextlib.suppress(Exception):  # the asker may be gone
                        query.reply(host_key(self.spec.fleet, self.name, topic), reply)

    def answer(self, topic: str, payload: bytes) -> bytes:
        """The JSON reply to a request on `topic`; refusals are counted, never raised."""
        self.requests += 1
        try:
            self._handle(topic, payload)
            reply = HostReply(ok=True, status=self.status())
        except (PhalanxError, ValidationError) as exc:
            reason = self._refusal(topic, exc)
            reply = HostReply(ok=False, error=reason, status=self.status())
        except Exception:  # the daemon must outlive any request
            log.exception("host %s: a %s request failed", self.name, topic)
            self.refused += 1
            error = "internal error: see the host's log"
            reply = HostReply(ok=False, error=error, status=self.status())
        return reply.model_dump_json().encode("utf-8")

    def _refusal(self, topic: str, exc: PhalanxError | ValidationError) -> str:
        self.refused += 1
        if isinstance(exc, ValidationError):
            reason = f"malformed {topic} request: {validation_summary(exc)}"
        else:
            reason = str(exc)
        log.warning("host %s refused a %s request: %s", self.name, topic, reason)
        return reason

    def _handle(self, topic: str, payload: bytes) -> None:
        if len(payload) > MAX_REQUEST_BYTES:
            raise RequestRefused(f"request of {len(payload)} bytes: at most {MAX_REQUEST_BYTES}")
        if topic not in ("spawn", "stop"):
            return
        operator = None
        if self.verifier is not None:  # secured: every request signed by a listed operator
            operator, payload = self.verifier.open(payload)
        model: type[SpawnRequest | StopRequest] = SpawnRequest if topic == "spawn" else StopRequest
        request = model.model_validate_json(payload)
        if self.verifier is not None:
            self.verifier.check_fresh(request.issued_unix)
        if isinstance(request, SpawnRequest):
            self.spawn(request, operator=operator)
        else:
            self.stop(request)

    # --- requests -----------------------------------------------------------------------

    def spawn(self, request: SpawnRequest, *, operator: str | None = None) -> None:
        """Start the requested processes of this host (idempotent for a running one);
        `operator`: who signed the request (a secured fleet), for the overrides' check.
        """
        self.checks.check_deployment(request.deployment, request.digest)
        robots = self.checks.requested_robots(request.robots)
        overrides = self.checks.checked_overrides(request.overrides, operator=operator)
        self.checks.check_epoch(request.epoch_unix)
        self._claim_run(request.run_id)
        world = request.world and self.spec.runs_world(self.name)
        self._check_not_elsewhere([*robots, *(["world"] if world else [])])
        run = RunParameters(request.run_id, request.epoch_unix, overrides)
        python = self.options.python
        for rid in robots:
            spec = agent_spec(self.loaded, rid, run=run)
            self._ensure(rid, "agent", spawn_argv(spec, python=python), spec=spec)
        if world:
            out = self._results_dir(request.run_id)
            self._ensure("world", "world", world_argv(self.loaded, run=run, out=out, python=python))
        if request.world and bridge_host(self.spec) == self.name:
            # (a bridge that crashes is started again, as an agent is)
            self._ensure(BRIDGE, "agent", bridge_argv(self.loaded, run=run, python=python))

    def stop(self, request: StopRequest) -> None:
        """Stop some or all of this host's processes (SIGTERM, then SIGKILL)."""
        self.checks.check_deployment(request.deployment, request.digest)
        if request.run_id is not None and request.run_id != self.run_id:
            raise RequestRefused(
                f"run {request.run_id!r} is not this host's (its run: {self.run_id!r})"
            )
        names = list(self.checks.requested_robots(request.robots))
        if request.world:
            names += ["world", BRIDGE]
        now = time.monotonic()
        for name in names:
            child = self.children.get(name)
            if child is not None:
                child.stop(now, self.options.grace_s)
                log.info("host %s: stopping %s", self.name, name)

    def _claim_run(self, run_id: str) -> None:
        busy = sorted(c.name for c in self.children.values() if c.active)
        if busy and run_id != self.run_id:
            raise RequestRefused(
                f"host {self.name!r} is running run {self.run_id!r} ({', '.join(busy)}): "
                "stop it first (phalanx stop)"
            )
        if run_id != self.run_id:
            self.children.clear()
            self.run_id = run_id

    def _check_not_elsewhere(self, names: list[str]) -> None:
        """Refuse to start what is already on the fabric but not our child.

        That is an orphan of a previous daemon, or the same robot started by another host.
        """
        with self._lock:
            alive = set(self._alive)
        for name in names:
            ours = self.children.get(name)
            if name in alive and (ours is None or not ours.active):
                raise RequestRefused(
                    f"{name} is already on the fabric of fleet {self.spec.fleet!r} (its "
                    "liveliness token is up) but not started by this host: stop it first"
                )

    def _results_dir(self, run_id: str) -> Path:
        world = self.spec.world
        base = Path(world.out_dir if world else "results")
        return (base if base.is_absolute() else self.options.workdir / base) / run_id

    def _ensure(
        self,
        name: str,
        kind: Literal["agent", "world"],
        argv: list[str],
        *,
        spec: AgentSpec | None = None,
    ) -> None:
        current = self.children.get(name)
        if current is not None and current.active:
            return
        child = ManagedChild(
            name, kind, argv, policy=self.spec.restart, on_line=self._on_line, spec=spec
        )
        self.children[name] = child
        self._publisher(name)
        self._start(child)

    def _start(self, child: ManagedChild) -> None:
        try:
            child.start(workdir=self.options.workdir)
        except OSError as exc:
            child.state, child.last_error = "failed", f"cannot start: {exc}"
            log.error("host %s: cannot start %s: %s", self.name, child.name, exc)
            return
        assert child.process is not None  # noqa: S101 - start() set it
        log.info("host %s: started %s (pid %d)", self.name, child.name, child.process.pid)

    # --- supervision --------------------------------------------------------------------

    def supervise(self) -> None:
        """Notice exits, restart crashed agents after their back-off, escalate stops."""
        now = time.monotonic()
        with self._lock:
            alive = set(self._alive)
        for child in list(self.children.values()):
            self._supervise_one(child, now, alive)

    def _supervise_one(self, child: ManagedChild, now: float, alive: set[str]) -> None:
        code = child.poll()
        if code is not None and child.state in ("starting", "running", "stopping"):
            self._ended(child, code, now)
        elif child.state == "starting" and child.name in alive:
            child.state = "running"
        elif child.state == "running" and now - child.started_at > child.policy.stable_s:
            child.backoff_steps = 0
        elif child.state == "stopping" and now > child.kill_at:
            child.signal(signal.SIGKILL)
        elif child.state == "backoff" and now >= child.restart_at:
            child.restarts += 1
            log.warning(
                "host %s: restarting %s (restart %d)", self.name, child.name, child.restarts
            )
            self._start(child)

    def _ended(self, child: ManagedChild, code: int, now: float) -> None:
        child.exit_code = code
        if child.state == "stopping":
            child.state = "stopped"
            return
        if code == 0 or (child.kind == "world" and code == EXIT_INCOMPLETE):
            child.state = "finished"  # (exit 5: a run its results mark incomplete, saying why)
            log.info("host %s: %s finished (exit %d)", self.name, child.name, code)
            return
        child.crashes += 1
        child.join_output(0.5)  # its last words are the likely reason
        last = child.last_error or (child.lines[-1] if child.lines else "")
        child.last_error = f"{exit_reason(code)}: {last}" if last else exit_reason(code)
        if child.kind == "world" and self.run_id is not None:
            self._mark_results(f"world: {exit_reason(code)}")
        if child.kind == "agent" and child.backoff_steps < child.policy.max_restarts:
            delay_s = backoff_delay_s(child.policy, child.backoff_steps)
            child.backoff_steps += 1
            child.state, child.restart_at = "backoff", now + delay_s
            log.error(
                "host %s: %s crashed (%s); restart in %.1f s",
                self.name,
                child.name,
                exit_reason(code),
                delay_s,
            )
        else:
            child.state = "failed"
            log.error("host %s: %s failed (%s)", self.name, child.name, exit_reason(code))

    def _mark_results(self, problem: str) -> None:
        """The world died: its results folder says so, with what survived."""
        from phalanx.analysis.results import mark_results

        assert self.run_id is not None  # noqa: S101 - checked by the caller
        folder = self._results_dir(self.run_id)
        try:
            mark_results(folder, problems=[problem])
        except OSError as exc:
            log.error("host %s: cannot mark %s incomplete: %s", self.name, folder, exc)

    def shutdown(self) -> None:
        """Stop every child: SIGTERM, SIGKILL after the grace period; bounded."""
        now = time.monotonic()
        for child in self.children.values():
            child.stop(now, self.options.grace_s)
        deadline = now + self.options.grace_s + 5.0
        while any(c.poll() is None for c in self._started_children()):
            if time.monotonic() > deadline:
                break
            self.supervise()  # escalates to SIGKILL after the grace period
            time.sleep(0.05)
        for child in self._started_children():
            with contextlib.suppress(subprocess.TimeoutExpired):
                if child.process is not None:
                    child.process.wait(1.0)
            child.join_output(0.5)
        self.supervise()  # record the last exits

    def _started_children(self) -> list[ManagedChild]:
        return [c for c in self.children.values() if c.process is not None]

    # --- output and status --------------------------------------------------------------

    def _publisher(self, name: str) -> Any:
        import zenoh

        if name not in self._publishers and self._session is not None:
            key = log_key(self.spec.fleet, self.name, name)
            publisher = self._session.zenoh.declare_publisher(
                key,
                congestion_control=zenoh.CongestionControl.DROP,
                priority=zenoh.Priority.DATA_LOW,
            )
            self._publishers[name] = self._session.hold(publisher)
        return self._publishers.get(name)

    def _on_line(self, child: ManagedChild, line: str, level: LogLevel) -> None:
        if self.options.echo:
            child_log.info("%s | %s", child.name, line)
        message = LogLine(
            host=self.name,
            child=child.name,
            run_id=self.run_id or "",
            time_unix=time.time(),
            level=level,
            line=line,
        )
        publisher = self._publishers.get(child.name)
        if publisher is not None:
            with contextlib.suppress(Exception):  # the session may be closing
                publisher.put(message.model_dump_json().encode("utf-8"))

    def status(self) -> HostStatus:
        """The host's status as the protocol reports it."""
        return HostStatus(
            host=self.name,
            fleet=self.spec.fleet,
            deployment=self.spec.name,
            digest=self.loaded.digest,
            time_unix=time.time(),
            uptime_s=time.monotonic() - self.started,
            run_id=self.run_id,
            robots=self.spec.robots_on(self.name),
            world=self.spec.runs_world(self.name),
            children=tuple(c.status() for c in self.children.values()),
            requests=self.requests,
            refused=self.refused,
            replays=self.verifier.replays if self.verifier is not None else 0,
        )


def _verifier(loaded: LoadedDeployment, host: str, options: DaemonOptions) -> RequestVerifier:
    """A secured daemon's check of its requests, its served ones kept in its state folder."""
    security = security_of(loaded.spec)
    state = options.state_dir or default_state_dir(loaded.spec.fleet, host)
    return RequestVerifier(
        ca_path(loaded), security.operators, security.request_window_s, state=state
    )


def _payload(query: Any) -> bytes:
    payload = query.payload
    return b"" if payload is None else bytes(payload.to_bytes())
