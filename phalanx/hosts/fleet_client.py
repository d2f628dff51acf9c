"""A client of a deployment's host daemons, behind `phalanx launch`, `status` and `stop`.

`FleetClient` is a Zenoh client of one host's daemon (this machine's, if it is one of the
hosts; else the router, or the first host it reaches). It waits (bounded) for every host
of the deployment to be present and to hold the same deployment and scenario files, asks
the hosts to spawn or stop their part of a run, and reads their status queryables.
`FleetWatch` collects what the fleet publishes: the robots' own state messages
(behaviour state, leader, publication rate) and the children's output (log lines the
daemons publish).
"""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from pydantic import ValidationError

from phalanx.core.config_files import load_robot
from phalanx.core.errors import DeploymentError, TransportError
from phalanx.core.lifecycle import Closing
from phalanx.hosts.deployment import LoadedDeployment
from phalanx.hosts.protocol import (
    ACTIVE_STATES,
    HostReply,
    HostStatus,
    LogLine,
    SpawnRequest,
    StopRequest,
)
from phalanx.hosts.request_auth import sign
from phalanx.hosts.wiring import client_transport
from phalanx.runtime.signals import Stoppable
from phalanx.wire.bounds import FleetBounds
from phalanx.wire.keys import (
    host_key,
    host_of,
    hosts_key,
    logs_key,
    robots_key,
    status_key,
    statuses_key,
)
from phalanx.wire.messages import RobotState
from phalanx.wire.transport import FleetSession, TransportConfig, open_session

RATE_WINDOW_S = 2.0
MAX_LOG_QUEUE = 10_000  # log lines waiting for the launcher's next look
ASK_TIMEOUT_S = 1.5


class FleetWatch:
    """Robot states and log lines as they arrive (Zenoh callbacks fill it, the loop reads)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.states: dict[str, RobotState] = {}
        self.first_seen: dict[str, float] = {}
        self._arrivals: dict[str, deque[float]] = {}
        self.logs: queue.Queue[LogLine] = queue.Queue(maxsize=MAX_LOG_QUEUE)
        self.hosts_present: set[str] = set()
        self.malformed_logs = 0
        self.dropped_logs = 0  # lines beyond MAX_LOG_QUEUE waiting (a flood)

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
            line = LogLine.model_validate_json(sample.payload.to_bytes())
            if line.host != host_of(str(sample.key_expr)):  # a line on another host's key
                self.malformed_logs += 1
                return
            self.logs.put_nowait(line)
        except ValidationError:
            self.malformed_logs += 1
        except queue.Full:
            self.dropped_logs += 1

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
        self.identity = transport.tls  # a secured fleet: requests are signed with it
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
        bounds = FleetBounds.of(self.loaded.scenario, load_robot(self.loaded.scenario.robot))
        self.session.subscribe(
            robots_key(fleet, "state"), RobotState, self.watch.on_state, context=bounds
        )
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

    def process_statuses(self, timeout_s: float = 0.5) -> dict[str, dict[str, Any]]:
        """Every fleet process's own status (its counters, drops included), by robot id
        ("world" for the world); a reply naming no process of the deployment is left out.
        """
        names = {r.id for r in self.spec.robots} | {"world"}
        out = {}
        for reply in self.session.query_status(statuses_key(self.spec.fleet), timeout_s):
            name = reply.get("robot_id", "world" if "tick" in reply else None)
            if isinstance(name, str) and name in names:
                out[name] = reply
        return out

    def wait_for_hosts(
        self, timeout_s: float, say: Callable[[str], None], stop: Stoppable | None = None
    ) -> dict[str, HostStatus]:
        """Every host's status once all are present; DeploymentError naming the missing.
        Empty if `stop` is set first (Ctrl-C while waiting).
        """
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
            if stop is None:
                time.sleep(0.1)
            elif stop.wait(0.1):
                return {}
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
            issued_unix=time.time(),
        )
        payload = self._signed(request.model_dump_json().encode("utf-8"))
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
        request = StopRequest(
            deployment=self.spec.name,
            digest=self.loaded.digest,
            run_id=run_id,
            issued_unix=time.time(),
        )
        payload = self._signed(request.model_dump_json().encode("utf-8"))
        present = [h for h in self.host_names if h in self.watch.present()]
        return self.ask("stop", dict.fromkeys(present, payload))

    def _signed(self, request: bytes) -> bytes:
        """The request as sent: signed by this client's identity on a secured fleet."""
        if not self.spec.secured or self.identity is None:
            return request
        return sign(request, self.identity)

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
