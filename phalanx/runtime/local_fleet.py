"""`phalanx up`: the world and one agent process per robot on this machine, supervised.

The world runs a Zenoh router on a free loopback port and every agent connects to it as
a client, so the world routes the agents' states to each other (multicast scouting
stays off; nothing is configured by hand). A crashed agent is reported and, with
`restart`, started again. Everything is stopped on the way out: SIGTERM first, SIGKILL
after a grace period.
"""

from __future__ import annotations

import logging
import signal
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from phalanx.core.config import Scenario
from phalanx.runtime.signals import Stoppable
from phalanx.wire.transport import free_tcp_port, loopback_endpoint

log = logging.getLogger("phalanx.up")
GRACE_S = 5.0


@dataclass
class UpOptions:
    """What `phalanx up` starts."""

    fleet: str
    clock: str = "lockstep"
    speed: float = 1.0
    out: Path | None = None
    restart: bool = False
    max_restarts: int = 3
    timeout_s: float = 600.0
    recording: bool = True
    extra_agent_args: tuple[str, ...] = ()
    overrides: tuple[str, ...] = ()
    driver: str = "sim"
    startup_s: float = 8.0  # robot drivers: time given to every process before step 0
    recording_id: str = field(default_factory=lambda: str(uuid.uuid4()))
    telemetry_url: str | None = None  # stream live to a viewer as well


@dataclass
class Child:
    """A supervised process."""

    name: str
    argv: list[str]
    process: subprocess.Popen[bytes] | None = None
    restarts: int = 0
    reported: bool = False
    exits: list[int] = field(default_factory=list)

    def start(self) -> None:
        """Start (again)."""
        self.reported = False
        self.process = subprocess.Popen(self.argv)  # noqa: S603 - our own interpreter and CLI

    def poll(self) -> int | None:
        """Exit code if it has ended."""
        return None if self.process is None else self.process.poll()


def _cli() -> list[str]:
    return [sys.executable, "-m", "phalanx"]


def plan(scenario_path: Path, scenario: Scenario, options: UpOptions) -> list[Child]:
    """The world and agent command lines."""
    endpoint = loopback_endpoint(free_tcp_port())
    common = ["--fleet", options.fleet, "--clock", options.clock, *options.overrides]
    world = [
        *_cli(),
        "world",
        str(scenario_path),
        *common,
        "--listen",
        endpoint,
        "--speed",
        str(options.speed),
    ]
    if options.out is not None:
        world += ["--out", str(options.out)]
    # The world's own post-run recording is replaced by every process's live one.
    world += ["--no-recording", *_telemetry_args(options, "world")]
    agent_extra: dict[str, list[str]] = {
        entry.id: _telemetry_args(options, entry.id) for entry in scenario.robots
    }
    emulators: list[Child] = []
    if options.driver == "arcos":
        epoch = time.time() + options.startup_s
        world += ["--epoch", f"{epoch:.3f}"]
        for entry in scenario.robots:
            port = free_tcp_port()
            emulators.append(Child(f"{entry.id}-emulator", [
                *_cli(), "emulate", "p3dx", "--tcp", str(port), "--world", str(scenario_path),
                "--robot", entry.id, "--fleet", options.fleet, "--connect", endpoint,
            ]))  # fmt: skip
            agent_extra[entry.id] += [
                "--driver", "arcos", "--arcos-tcp", f"127.0.0.1:{port}", "--epoch", f"{epoch:.3f}",
            ]  # fmt: skip
    children = [Child("world", world), *emulators]
    for entry in scenario.robots:
        agent = [
            *_cli(),
            "agent",
            str(scenario_path),
            "--robot",
            entry.id,
            *common,
            "--mode",
            "client",
            "--connect",
            endpoint,
            *agent_extra[entry.id],
            *options.extra_agent_args,
        ]
        children.append(Child(entry.id, agent))
    return children


def _telemetry_args(options: UpOptions, name: str) -> list[str]:
    args = []
    if options.recording and options.out is not None:
        args += ["--telemetry-file", str(telemetry_dir(options.out) / f"{name}.rrd")]
    if options.telemetry_url:
        args += ["--telemetry-url", options.telemetry_url]
    return ["--recording-id", options.recording_id, *args] if args else []


def telemetry_dir(out: Path) -> Path:
    """Where every process of a run writes its part of the recording."""
    return out / "telemetry"


def merge_recordings(parts: list[Path], target: Path, timeout_s: float = 120.0) -> bool:
    """Merge the processes' .rrd files into one (the same recording id: one recording).

    A part without a footer (its process was killed) is merged as far as it goes.
    """
    from phalanx.telemetry.sinks import rerun_executable

    command = [rerun_executable(), "rrd", "merge", "--continue-on-error"]
    try:
        subprocess.run(  # noqa: S603 - rerun's own CLI, our paths
            [*command, "-o", str(target), *map(str, parts)],
            check=True,
            capture_output=True,
            timeout=timeout_s,
        )
    except (OSError, subprocess.SubprocessError) as exc:
        log.error("could not merge the recording parts into %s: %s", target, exc)
        return False
    return True


def start_viewer(port: int | None = None) -> str:
    """Start `phalanx view` in the background (it outlives the run); its gRPC url."""
    port = port or free_tcp_port()
    subprocess.Popen(  # noqa: S603 - our own CLI
        [*_cli(), "view", "--port", str(port)], start_new_session=True
    )
    time.sleep(1.0)  # the SDK buffers until it connects, but a listening viewer is quicker
    return f"rerun+http://127.0.0.1:{port}/proxy"


def stop_all(children: list[Child]) -> None:
    """SIGTERM every live child, then SIGKILL what is left after the grace period."""
    live = [c.process for c in children if c.process is not None and c.process.poll() is None]
    for proc in live:
        proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + GRACE_S
    for proc in live:
        try:
            proc.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5.0)


def supervise(children: list[Child], options: UpOptions, stop: Stoppable) -> int:
    """Run until the world ends; returns the world's exit code (or 1 on timeout/stop)."""
    for child in children:
        child.start()
    world, agents = children[0], children[1:]
    deadline = time.monotonic() + options.timeout_s
    try:
        while not stop.is_set() and time.monotonic() < deadline:
            code = world.poll()
            if code is not None:
                return code
            for agent in agents:
                _check_agent(agent, options)
            time.sleep(0.1)
        log.error("stopping the fleet: %s", "interrupted" if stop.is_set() else "timed out")
        return 1
    finally:
        stop_all(children)


def _check_agent(agent: Child, options: UpOptions) -> None:
    code = agent.poll()
    if code is None or agent.reported:
        return
    agent.reported = True
    if code == 0:
        return
    agent.exits.append(code)
    log.error("agent %s exited with %d", agent.name, code)
    if options.restart and agent.restarts < options.max_restarts:
        agent.restarts += 1
        time.sleep(min(2.0, 0.2 * 2**agent.restarts))
        log.warning("restarting agent %s (restart %d)", agent.name, agent.restarts)
        agent.start()
