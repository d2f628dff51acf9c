"""A fleet of real processes to attack: the world and three agents of the paper wedge over
Zenoh on loopback (multicast scouting off), started through the CLI as a user would,
with a client session beside them that injects payloads and watches what the robots
publish. Used by the fault tier (`tests/faults`) and by `bench/bench_faults.py`.

Every process's output goes to its own file, so a probe can say which crashed and why
(a Python traceback in the output, or an exit code other than the expected ones).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from phalanx.core.config_files import CONFIG_ROOT
from phalanx.wire.keys import leader_key, robots_key
from phalanx.wire.transport import FleetSession, TransportConfig, free_tcp_port, open_session

WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
CLI = [sys.executable, "-m", "phalanx"]
ROBOTS = ("r1", "r2", "r3")


def wait_for(predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.01) -> bool:
    """Poll `predicate` until it holds or `timeout_s` passes; whether it held."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll_s)
    return bool(predicate())


@dataclass
class Seen:
    """One robot state as the watcher decoded it: arrival (monotonic) and the fields."""

    at: float
    state: Any


@dataclass
class Watcher:
    """Every robot's states and the leadership announcements, as they arrive."""

    states: dict[str, list[Seen]] = field(default_factory=dict)
    announcements: list[Any] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_state(self, _key: str, state: Any) -> None:
        """A state decoded (Zenoh thread)."""
        with self.lock:
            self.states.setdefault(state.robot_id, []).append(Seen(time.monotonic(), state))

    def on_announcement(self, _key: str, message: Any) -> None:
        """A leadership announcement decoded (Zenoh thread)."""
        with self.lock:
            self.announcements.append(message)

    def latest(self, rid: str) -> Seen | None:
        """The last state of `rid`."""
        with self.lock:
            seen = self.states.get(rid)
            return seen[-1] if seen else None

    def since(self, rid: str, t: float) -> list[Seen]:
        """States of `rid` that arrived after monotonic time `t`."""
        with self.lock:
            return [s for s in self.states.get(rid, ()) if s.at > t]


class Fleet:
    """The world (a Zenoh router on a free port) and one agent process per robot."""

    def __init__(
        self,
        workdir: Path,
        *,
        fleet: str,
        clock: str = "realtime",
        duration_s: float = 60.0,
        sets: tuple[str, ...] = (),
        scenario: Path = WEDGE,
        world_args: tuple[str, ...] = (),
    ) -> None:
        self.workdir, self.fleet, self.clock = workdir, fleet, clock
        self.scenario = scenario
        self.endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.out = workdir / "out"
        self.common = ["--fleet", fleet, "--clock", clock, "--set", f"duration_s={duration_s}"]
        self.common += [a for s in sets for a in ("--set", s)]
        self.world_args = world_args
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.watch = Watcher()
        self.session: FleetSession | None = None

    # --- processes ----------------------------------------------------------------------

    def argv(self, name: str) -> list[str]:
        """The command line of the world or of robot `name`'s agent."""
        if name == "world":
            return [
                *CLI,
                "world",
                str(self.scenario),
                *self.common,
                "--listen",
                self.endpoint,
                "--out",
                str(self.out),
                "--no-recording",
                *self.world_args,
            ]
        return [
            *CLI,
            "agent",
            str(self.scenario),
            "--robot",
            name,
            *self.common,
            "--mode",
            "client",
            "--connect",
            self.endpoint,
        ]

    def log_path(self, name: str) -> Path:
        """Where process `name`'s output goes (appended on a restart)."""
        return self.workdir / f"{name}.log"

    def start(self, name: str) -> subprocess.Popen[bytes]:
        """Start (or restart) the world or robot `name`."""
        with self.log_path(name).open("ab") as out:
            proc = subprocess.Popen(self.argv(name), stdout=out, stderr=subprocess.STDOUT)
        self.procs[name] = proc
        return proc

    def start_all(self) -> None:
        """The world first (it is the router), then the agents."""
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.start("world")
        for rid in ROBOTS:
            self.start(rid)

    def signal(self, name: str, sig: int) -> None:
        """Send `sig` to process `name`."""
        self.procs[name].send_signal(sig)

    def exit_codes(self) -> dict[str, int | None]:
        """Each process's exit code (None: still running)."""
        return {name: proc.poll() for name, proc in self.procs.items()}

    def tracebacks(self) -> dict[str, int]:
        """Python tracebacks printed by each process so far."""
        out = {}
        for name in self.procs:
            path = self.log_path(name)
            text = path.read_text(errors="replace") if path.exists() else ""
            out[name] = text.count("Traceback (most recent call last)")
        return out

    def tails(self, lines: int = 15) -> str:
        """The last lines of every process's output, for a failure's message."""
        told = ""
        for name in self.procs:
            path = self.log_path(name)
            text = path.read_text(errors="replace") if path.exists() else ""
            told += f"\n--- {name}\n" + "\n".join(text.splitlines()[-lines:])
        return told

    def crashed(self, *, allowed: tuple[int, ...] = (0,)) -> list[str]:
        """Processes that printed a traceback or ended with an unexpected code."""
        codes, traces = self.exit_codes(), self.tracebacks()
        bad = [n for n, c in codes.items() if c is not None and c not in allowed]
        return sorted(set(bad) | {n for n, k in traces.items() if k})

    def wait_exit(self, name: str, timeout_s: float) -> int | None:
        """Wait (bounded) for process `name` to end; its exit code."""
        try:
            return self.procs[name].wait(timeout_s)
        except subprocess.TimeoutExpired:
            return None

    def stop(self) -> None:
        """SIGTERM every process (SIGCONT first: one may be frozen), SIGKILL after 10 s."""
        terminate(self.procs.values(), grace_s=10.0)

    # --- the observer's session ---------------------------------------------------------

    def connect(self) -> FleetSession:
        """A client session on the fleet's router, watching states and announcements."""
        from phalanx.wire.messages import LeaderAnnouncement, RobotState

        # (the world's router comes up once its process has imported phalanx, which takes
        # a loaded machine far longer than the session's default 15 s)
        config = TransportConfig(mode="client", connect=(self.endpoint,), open_timeout_s=60.0)
        session = open_session(config)
        session.subscribe(robots_key(self.fleet, "state"), RobotState, self.watch.on_state)
        session.subscribe(leader_key(self.fleet), LeaderAnnouncement, self.watch.on_announcement)
        self.session = session
        return session

    def wait_tracking(self, timeout_s: float = 60.0, after_s: float = 3.0) -> bool:
        """Whether both followers track the leader (stamped after `after_s`) in time."""

        def tracking() -> bool:
            for rid in ("r2", "r3"):
                seen = self.watch.latest(rid)
                if seen is None or seen.state.fsm_state != "FORMATION_TRACK":
                    return False
                if seen.state.stamp_s <= after_s:
                    return False
            return True

        return wait_for(tracking, timeout_s)

    def status(self, name: str = "*", timeout_s: float = 2.0) -> list[dict[str, Any]]:
        """Status replies of process `name` (or every process)."""
        assert self.session is not None
        return self.session.query_status(f"phalanx/{self.fleet}/status/{name}", timeout_s)


@contextmanager
def running_fleet(workdir: Path, **kwargs: Any) -> Iterator[Fleet]:
    """A started fleet with its observer session; everything stopped and closed after."""
    fleet = Fleet(workdir, **kwargs)
    try:
        fleet.start_all()
        with fleet.connect():
            yield fleet
    finally:
        fleet.stop()


def children_of(pid: int) -> list[int]:
    """Direct child processes of `pid` (from /proc)."""
    pids: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            pids += [int(p) for p in (task / "children").read_text().split()]
        except (FileNotFoundError, ProcessLookupError):
            continue
    return pids


def cmdline(pid: int) -> list[str]:
    """The command line of `pid` ([] if it is gone)."""
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except FileNotFoundError:
        return []
    return [part.decode(errors="replace") for part in raw.split(b"\0") if part]


def child_running(parent: int, *needle: str) -> int | None:
    """The pid of `parent`'s child whose command line holds every `needle`, if any."""
    for pid in children_of(parent):
        argv = cmdline(pid)
        if all(n in argv for n in needle):
            return pid
    return None


# --- a deployment on loopback: three host daemons, optionally through a router ------------

HOSTS = ("laptop", "robot-a", "robot-b")
PLACEMENT = {"r1": "robot-a", "r2": "robot-b", "r3": "robot-b"}


def deployment_file(
    workdir: Path, *, name: str, duration_s: float, router: bool = False, recording: bool = True
) -> tuple[Path, int | None]:
    """The paper wedge on three loopback hosts (the world on `laptop`), every host linked
    through a `phalanx router` if `router`; the file and the router's port."""
    router_port = free_tcp_port() if router else None
    lines = [
        f'name = "{name}"', f'fleet = "{name}"', f'scenario = "{WEDGE}"', 'clock = "realtime"',
        f'overrides = ["duration_s={duration_s}"]',
        "[zenoh]", "lease_ms = 500", "retry_max_ms = 250",
    ]  # fmt: skip
    if router_port is not None:
        lines.append(f'router = {{ address = "127.0.0.1", port = {router_port} }}')
    lines += ["[world]", 'host = "laptop"', f'out_dir = "{workdir / "results"}"',
              f"recording = {'true' if recording else 'false'}"]  # fmt: skip
    for host in HOSTS:
        lines += [
            "[[hosts]]",
            f'name = "{host}"',
            'address = "127.0.0.1"',
            f"port = {free_tcp_port()}",
        ]
    for rid, host in PLACEMENT.items():
        lines += ["[[robots]]", f'id = "{rid}"', f'host = "{host}"']
    path = workdir / f"{name}.toml"
    path.write_text("\n".join(lines) + "\n")
    return path, router_port


@dataclass
class Hosts:
    """Host daemons (and a router) started by a test, each with its log file."""

    workdir: Path
    deployment: Path
    procs: dict[str, subprocess.Popen[bytes]] = field(default_factory=dict)

    def start(self, name: str) -> subprocess.Popen[bytes]:
        """Start host `name`'s daemon, or the router (`name` "router")."""
        argv = [*CLI, "router", str(self.deployment)] if name == "router" else [
            *CLI, "host", str(self.deployment), "--name", name, "--quiet"]  # fmt: skip
        with (self.workdir / f"host-{name}.log").open("ab") as out:
            self.procs[name] = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT)
        return self.procs[name]

    def log(self, name: str) -> str:
        """Host `name`'s log so far."""
        path = self.workdir / f"host-{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def stop(self) -> None:
        """SIGTERM every daemon and the router (SIGCONT first), SIGKILL after 20 s."""
        terminate(self.procs.values(), grace_s=20.0)


@contextmanager
def running_hosts(workdir: Path, deployment: Path, *, router: bool) -> Iterator[Hosts]:
    """The deployment's daemons (and its router) running; all stopped after."""
    hosts = Hosts(workdir, deployment)
    try:
        if router:
            hosts.start("router")
        for name in HOSTS:
            hosts.start(name)
        yield hosts
    finally:
        hosts.stop()


def terminate(procs: Iterable[subprocess.Popen[Any]], *, grace_s: float) -> None:
    """SIGTERM every live process (SIGCONT first: one may be frozen); SIGKILL any still
    running after `grace_s`.
    """
    running = list(procs)
    for proc in running:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGCONT)
            proc.send_signal(signal.SIGTERM)
    for proc in running:
        try:
            proc.wait(grace_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


# --- a flood of one key, from a process of its own ----------------------------------------

FLOOD_BATCH = 100  # puts between two looks at the clock


def flood(
    endpoint: str, key: str, *, after: int, seconds: float, rate_hz: float = 0.0
) -> dict[str, float]:
    """Copies of the `after`-th payload heard on `key` (a valid message, soon old), put
    back on `key` at `rate_hz` (0: as fast as this process can) for `seconds` or until
    SIGTERM: how many were put, over how long (s), at what rate (Hz). The capture waits
    at most 60 s (nothing heard: nothing put).
    """
    import queue

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    heard: queue.Queue[bytes] = queue.Queue()
    with open_session(TransportConfig(mode="client", connect=(endpoint,))) as session:
        sub = session.zenoh.declare_subscriber(key, lambda s: heard.put(s.payload.to_bytes()))
        payload, taken, deadline = b"", 0, time.monotonic() + 60.0
        while taken < after and not stop.is_set() and time.monotonic() < deadline:
            try:
                payload, taken = heard.get(timeout=0.1), taken + 1
            except queue.Empty:
                continue
        sub.undeclare()
        if taken < after:
            return {"sent": 0, "seconds": 0.0, "rate_hz": 0.0}
        publisher = session.zenoh.declare_publisher(key)
        sent, began = 0, time.monotonic()
        due, end = began, began + seconds
        while not stop.is_set():
            for _ in range(FLOOD_BATCH):
                publisher.put(payload)
            sent += FLOOD_BATCH
            now = time.monotonic()
            if now >= end:
                break
            if rate_hz > 0.0:  # paced: behind by a second at most, never a burst to catch up
                due = max(due + FLOOD_BATCH / rate_hz, now - 1.0)
                stop.wait(max(0.0, due - now))
        took = time.monotonic() - began
        publisher.undeclare()
    return {"sent": sent, "seconds": took, "rate_hz": sent / max(took, 1e-9)}


def start_flooder(
    endpoint: str, key: str, *, after: int, seconds: float, rate_hz: float, out: Path
) -> subprocess.Popen[bytes]:
    """`flood` in a process of its own: its result as JSON in `out` (written when it
    ends, SIGTERM included), its output in `out` with the suffix `.log`.
    """
    argv = [sys.executable, __file__, "flood", endpoint, key]
    argv += [str(after), str(seconds), str(rate_hz), str(out)]
    with out.with_suffix(".log").open("ab") as sink:
        return subprocess.Popen(argv, stdout=sink, stderr=subprocess.STDOUT)


if __name__ == "__main__" and sys.argv[1:2] == ["flood"]:
    import json

    _endpoint, _key, _after, _seconds, _rate, _out = sys.argv[2:8]
    _result = flood(
        _endpoint, _key, after=int(_after), seconds=float(_seconds), rate_hz=float(_rate)
    )
    Path(_out).write_text(json.dumps(_result))
