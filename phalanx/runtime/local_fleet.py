"""`phalanx up`: the world and one agent process per robot on this machine, supervised.

The world runs a Zenoh router and every agent connects to it as a client, so the world
routes the agents' states to each other (multicast scouting stays off; nothing is
configured by hand). The router listens on one Unix-domain socket and nowhere else (no
TCP port), in a directory made for the run with mode 0700 and removed after it
(`private_fabric`): a process of another user cannot reach the socket, so it can neither
join the fleet nor publish on it; every process `up` starts (world, agents, emulators)
connects there.

Every agent is started from its spec (`phalanx.runtime.process_spec`), handed on its
standard input, not from options. With the scenario's `[ros2] enabled`, the ROS 2 bridge
(`phalanx ros2`) runs with them: it reads the fleet on the same private socket (it is
this user's process) and meets ROS 2's nodes at `[ros2] connect`, rmw_zenoh's own router
by default, on a session of its own. A crashed agent (or bridge) is reported and, with
`restart`, started again. Everything is stopped
on the way out: SIGTERM first, SIGKILL after a grace period. The outcome says whether
the run ended as asked (the world finished, no process died on its own) and, if not,
which process ended how; a world that finished a run its results mark incomplete
(exit 5) ended as asked: the results say why.

In lockstep every process is pinned to one CPU, round robin over the CPUs this one may
use (the world on the first): a tick wakes every process in turn, and a process that
comes back to the core it left finds its caches warm (on a 2-core machine the paper
run's ticks take about 11 % less wall time; `bench/bench_lockstep.py` measures both).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from phalanx.core.config import ROS_ROUTER, Scenario
from phalanx.core.errors import TransportError
from phalanx.runtime.amrisim import AmrisimCommand, amrisim_map, amrisim_ports
from phalanx.runtime.exits import (
    EXIT_FAILED,
    EXIT_FINISHED,
    EXIT_INCOMPLETE,
    agent_exit_reason,
)
from phalanx.runtime.process_spec import (
    AgentSpec,
    DriverChoice,
    TelemetryTarget,
    hand_spec,
    spawn_argv,
)
from phalanx.runtime.signals import Stoppable, supervised_env
from phalanx.wire.transport import (
    LOWLATENCY_MAX_BYTES,
    SOCKET_PATH_MAX_BYTES,
    TransportConfig,
    free_tcp_port,
    unix_socket_endpoint,
)

log = logging.getLogger("phalanx.up")
GRACE_S = 5.0
FABRIC_PREFIX = "phalanx-fleet-"  # + tempfile's 8 random characters
SOCKET_NAME = "zenoh.sock"
# `plan` without an endpoint: command lines to look at. A fleet started with them cannot
# open anything (no directory can exist under /dev/null), rather than an open one.
UNMADE_ENDPOINT = unix_socket_endpoint(Path("/dev/null") / SOCKET_NAME)


@dataclass
class UpOptions:
    """What `phalanx up` starts."""

    fleet: str
    clock: Literal["lockstep", "realtime"] = "lockstep"
    speed: float = 1.0
    out: Path | None = None
    restart: bool = False
    max_restarts: int = 3
    timeout_s: float = 600.0
    recording: bool = True
    overrides: tuple[str, ...] = ()  # scenario fields, `PATH=VALUE` as `--set` takes them
    driver: str = "sim"
    startup_s: float = 8.0  # robot drivers: time given to every process before step 0
    recording_id: str = field(default_factory=lambda: str(uuid.uuid4()))
    telemetry_url: str | None = None  # stream live to a viewer as well
    pin: bool | None = None  # one CPU per process, round robin (None: in lockstep)
    amrisim: AmrisimRun | None = None  # the robots are AMRISim's, not the world's

    @property
    def pinned(self) -> bool:
        """Whether the processes are pinned to CPUs."""
        return self.clock == "lockstep" if self.pin is None else self.pin


@dataclass(frozen=True)
class AmrisimRun:
    """An AMRISim to start as the run's robots, and the X display it draws on."""

    command: AmrisimCommand
    display: str


@dataclass
class Child:
    """A supervised process: one of ours (`kind` agent, emulator, world or bridge; an
    agent with its `spec`, written to its standard input at each start), or a third
    party's (`env` given: a simulator such as AMRISim, its output to `output`).
    """

    name: str
    argv: list[str]
    kind: str = "agent"
    spec: AgentSpec | None = None
    env: dict[str, str] | None = None
    output: Path | None = None  # a third party's stdout and stderr (None: ours, inherited)
    process: subprocess.Popen[bytes] | None = None
    restarts: int = 0
    reported: bool = False
    exits: list[int] = field(default_factory=list)  # unexpected exit codes, in order
    started_at: float = 0.0
    cpu: int | None = None  # the one CPU it runs on (None: any)

    def start(self) -> None:
        """Start (again), on its CPU if it has one."""
        self.reported = False
        self.started_at = time.monotonic()
        if self.env is None:
            stdin = None if self.spec is None else subprocess.PIPE
            self.process = subprocess.Popen(  # noqa: S603 - our own interpreter and CLI
                self.argv, env=supervised_env(), stdin=stdin
            )
            if self.spec is not None:
                hand_spec(self.process, self.spec)
        else:
            self.process = self._third_party(self.env)
        if self.cpu is not None:
            # (the interpreter has just started: its threads, Zenoh's among them, are
            # created later and inherit the main thread's CPU)
            pin_process(self.process.pid, self.cpu, self.name)

    def _third_party(self, env: dict[str, str]) -> subprocess.Popen[bytes]:
        """Start a program that is not ours: killed with `phalanx up` (it cannot watch
        its parent itself), its output to a file.
        """
        from phalanx.runtime.amrisim import die_with_us

        with contextlib.ExitStack() as files:
            sink = files.enter_context(open(self.output, "ab")) if self.output else None
            return subprocess.Popen(  # noqa: S603 - the user's own build of it
                self.argv, env=env, stdin=subprocess.DEVNULL,
                stdout=sink or subprocess.DEVNULL, stderr=sink or subprocess.DEVNULL,
                preexec_fn=die_with_us,  # (no thread runs yet in `phalanx up`)
            )  # fmt: skip

    def poll(self) -> int | None:
        """Exit code if it has ended."""
        return None if self.process is None else self.process.poll()


def usable_cpus() -> list[int]:
    """The CPUs this process may run on (empty where the platform cannot tell)."""
    getaffinity = getattr(os, "sched_getaffinity", None)
    return sorted(getaffinity(0)) if getaffinity is not None else []


def assign_cpus(children: list[Child], cpus: list[int]) -> None:
    """One CPU per child, `children` the world first, then the rest (the agents in the
    order it sends them their frames): as many on each CPU as round robin puts there,
    the world on the first, and those that share the world's CPU last (a robot woken on
    the world's CPU takes it from the world until it has answered, so its frame goes
    out after the others'). Nothing with fewer than two CPUs: there is nothing to choose.
    """
    if len(cpus) < 2:
        return
    world, *agents = children
    world.cpu = cpus[0]
    shares = sorted(
        (cpus[(i + 1) % len(cpus)] for i in range(len(agents))), key=lambda c: c == cpus[0]
    )
    for agent, cpu in zip(agents, shares, strict=True):
        agent.cpu = cpu


def pin_process(pid: int, cpu: int, name: str) -> bool:
    """Run process `pid` on `cpu` alone; a platform or a container that does not allow
    it is logged and the process runs wherever the system puts it.
    """
    setaffinity = getattr(os, "sched_setaffinity", None)
    if setaffinity is None:
        return False
    try:
        setaffinity(pid, {cpu})
    except OSError as exc:
        log.warning("could not pin %s to CPU %d (it runs unpinned): %s", name, cpu, exc)
        return False
    return True


def _cli() -> list[str]:
    return [sys.executable, "-m", "phalanx"]


def _frames_fit_lowlatency(scenario: Scenario) -> bool:
    from phalanx.core.config_files import load_robot
    from phalanx.runtime.world_frames import lockstep_frame_bytes
    from phalanx.simulator.world import World

    world = World.for_scenario(scenario, load_robot(scenario.robot))
    ids = [r.id for r in scenario.robots]
    return lockstep_frame_bytes(world, ids, scenario.dt_s) <= LOWLATENCY_MAX_BYTES


@contextlib.contextmanager
def private_fabric() -> Iterator[str]:
    """The Zenoh endpoint of one run: a Unix-domain socket in a directory made for it,
    mode 0700, under $XDG_RUNTIME_DIR when that is this user's own, else the temporary
    folder; the directory and all in it removed on the way out.

    Only this user (and root) can open the directory, so only their processes can
    connect to the socket. A TransportError if no private directory could be made.
    """
    folder = _private_dir()
    try:
        yield unix_socket_endpoint(folder / SOCKET_NAME)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _private_dir() -> Path:
    """A new directory only this user can open, whose socket path fits an address."""
    tail = Path(FABRIC_PREFIX + "x" * 8) / SOCKET_NAME
    for parent in _socket_parents():
        if len(os.fsencode(parent / tail)) > SOCKET_PATH_MAX_BYTES:
            continue
        try:
            folder = Path(tempfile.mkdtemp(prefix=FABRIC_PREFIX, dir=parent))  # 0700, new
        except OSError as exc:  # (gone, read-only, full)
            log.warning("cannot make the fleet's directory in %s: %s", parent, exc)
            continue
        if _private(folder):
            return folder
        shutil.rmtree(folder, ignore_errors=True)
    raise TransportError(
        "cannot make a private directory for the fleet's socket (tried "
        f"{', '.join(map(str, _socket_parents()))}; a socket path holds at most "
        f"{SOCKET_PATH_MAX_BYTES} bytes): set TMPDIR to a short local folder"
    )


def _socket_parents() -> list[Path]:
    """Where the run's directory may go: the user's runtime directory if it is theirs
    alone, the temporary folder, /tmp.
    """
    runtime = os.environ.get("XDG_RUNTIME_DIR", "")
    parents = [Path(runtime)] if runtime and _private(Path(runtime)) else []
    return [*parents, Path(tempfile.gettempdir()), Path("/tmp")]  # noqa: S108 - a last resort


def _private(folder: Path) -> bool:
    """Whether `folder` is a real directory (not a link) of this user that no one else
    may open.
    """
    try:
        info = folder.lstat()
    except OSError:
        return False
    mine = info.st_uid == os.geteuid()
    return stat.S_ISDIR(info.st_mode) and mine and info.st_mode & 0o077 == 0


def plan(
    scenario_path: Path, scenario: Scenario, options: UpOptions, *, endpoint: str = UNMADE_ENDPOINT
) -> list[Child]:
    """The world's command line and every agent's spec: the world listening on `endpoint`
    alone (from `private_fabric`), every other process connecting there (by default a
    socket that cannot be made: a plan to look at, not to run).
    """
    # Every process on this machine: Zenoh's low-latency transport (see TransportConfig),
    # if its messages carry the fleet's lockstep frames.
    lowlatency = options.clock != "lockstep" or _frames_fit_lowlatency(scenario)
    common = ["--fleet", options.fleet, "--clock", options.clock]
    common += ["--lowlatency"] if lowlatency else []
    common += [f"--set={o}" for o in options.overrides]
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
    # The world's own post-run recording is replaced by every process's live one, and
    # `phalanx up` names the results folder itself once every process has ended.
    world += ["--no-recording", "--no-results-line", *_telemetry_args(options, "world")]
    drivers: dict[str, DriverChoice] = {}
    emulators: list[Child] = []
    epoch: float | None = None
    if options.driver == "arcos":
        epoch = _epoch(options)
        world += ["--epoch", f"{epoch:.3f}"]
        for entry in scenario.robots:
            port = free_tcp_port()
            emulators.append(Child(f"{entry.id}-emulator", [
                *_cli(), "emulate", "p3dx", "--tcp", str(port), "--world", str(scenario_path),
                "--robot", entry.id, "--fleet", options.fleet, "--connect", endpoint,
                "--epoch", f"{epoch:.3f}",
            ]))  # fmt: skip
            drivers[entry.id] = DriverChoice(name="arcos", settings={"tcp": f"127.0.0.1:{port}"})
    if options.amrisim is not None:
        epoch = _epoch(options)
        world += ["--epoch", f"{epoch:.3f}"]
        world += [arg for entry in scenario.robots for arg in ("--observe", entry.id)]
        emulators.append(_amrisim_child(scenario, options.amrisim, options.out))
        ids = tuple(entry.id for entry in scenario.robots)
        ports = amrisim_ports(ids, options.amrisim.command.base_port)
        for rid in ids:
            settings = {"tcp": f"127.0.0.1:{ports[rid]}", "place_at": _place_at(scenario, rid)}
            drivers[rid] = DriverChoice(name="arcos", settings=settings)
    transport = TransportConfig(mode="client", connect=(endpoint,), lowlatency=lowlatency)
    children = [Child("world", world), *emulators]
    for entry in scenario.robots:
        spec = AgentSpec(
            scenario=scenario_path, overrides=options.overrides, robot_id=entry.id,
            fleet=options.fleet, clock=options.clock, transport=transport,
            driver=drivers.get(entry.id, DriverChoice()), epoch_s=epoch,
            telemetry=_telemetry_target(options, entry.id),
        )  # fmt: skip
        children.append(Child(entry.id, spawn_argv(spec, python=sys.executable), spec=spec))
    if options.pinned:
        assign_cpus(children, usable_cpus())
    if scenario.ros2.enabled:  # (on no CPU of its own: it does not pace the fleet)
        children.append(_bridge_child(scenario_path, scenario, options, transport))
    return children


def _bridge_child(
    scenario_path: Path, scenario: Scenario, options: UpOptions, fleet: TransportConfig
) -> Child:
    """`phalanx ros2`: a client of the fleet's router like the agents (`fleet`), meeting
    ROS 2 at `[ros2] connect`, or at rmw_zenoh's default router.
    """
    argv = [*_cli(), "ros2", str(scenario_path), "--fleet", options.fleet, "--mode", "client"]
    argv += [arg for endpoint in fleet.connect for arg in ("--connect", endpoint)]
    argv += ["--lowlatency"] if fleet.lowlatency else []
    argv += [f"--set={o}" for o in options.overrides]
    for endpoint in scenario.ros2.connect or (ROS_ROUTER,):
        argv += ["--ros-connect", endpoint]
    return Child("ros2-bridge", argv, kind="bridge")


def _epoch(options: UpOptions) -> float:
    """Step 0 of a run of robots on drivers, to the millisecond, as the world's command
    line gives it (`--epoch`): every process starts its clock at the same instant.
    """
    return round(time.time() + options.startup_s, 3)


def _amrisim_child(scenario: Scenario, run: AmrisimRun, out: Path | None) -> Child:
    """AMRISim with every robot of `scenario`, its map written first."""
    command = run.command
    command.map_path.parent.mkdir(parents=True, exist_ok=True)
    command.map_path.write_text(amrisim_map(scenario), encoding="utf-8")
    output = out / "amrisim.out" if out is not None else None
    argv = command.argv(scenario)
    return Child("amrisim", argv, kind="simulator", env=command.env(run.display), output=output)


def _place_at(scenario: Scenario, robot_id: str) -> tuple[float, float, float]:
    """The robot's start pose as the arcos driver's `place_at` (m, m, deg)."""
    pose = scenario.start_pose(robot_id)
    return (pose.x_m, pose.y_m, math.degrees(pose.theta_rad))


def _telemetry_target(options: UpOptions, name: str) -> TelemetryTarget:
    """Where process `name` sends its telemetry: its part of the recording in the
    results folder, the live viewer, both or nowhere, under the run's recording id.
    """
    file = None
    if options.recording and options.out is not None:
        file = telemetry_dir(options.out) / f"{name}.rrd"
    url = options.telemetry_url or None
    recording_id = options.recording_id if file or url else None
    return TelemetryTarget(recording_id=recording_id, file=file, url=url)


def _telemetry_args(options: UpOptions, name: str) -> list[str]:
    target = _telemetry_target(options, name)
    args = [] if target.file is None else ["--telemetry-file", str(target.file)]
    args += [] if target.url is None else ["--telemetry-url", target.url]
    return ["--recording-id", options.recording_id, *args] if args else []


def telemetry_dir(out: Path) -> Path:
    """Where every process of a run writes its part of the recording."""
    return out / "telemetry"


def merge_recordings(parts: list[Path], target: Path, timeout_s: float = 120.0) -> bool:
    """Merge the processes' .rrd files into one (the same recording id: one recording),
    under a temporary name renamed to `target` once whole (a failed merge, a full disk,
    leaves `target` as it was).

    A part without a footer (its process was killed) is merged as far as it goes.
    """
    from phalanx.telemetry.sinks import rerun_executable

    command = [rerun_executable(), "rrd", "merge", "--continue-on-error"]
    partial = target.with_name(f".{target.name}.tmp")
    try:
        subprocess.run(  # noqa: S603 - rerun's own CLI, our paths
            [*command, "-o", str(partial), *map(str, parts)],
            check=True,
            capture_output=True,
            timeout=timeout_s,
        )
        os.replace(partial, target)
    except (OSError, subprocess.SubprocessError) as exc:
        log.error("could not merge the recording parts into %s: %s", target, _why(exc))
        return False
    finally:
        with contextlib.suppress(OSError):
            partial.unlink()
    return True


def _why(exc: OSError | subprocess.SubprocessError) -> str:
    """An error in a line: a failed command by its own last words."""
    if isinstance(exc, subprocess.CalledProcessError) and exc.stderr:
        lines = exc.stderr.decode("utf-8", "replace").strip().splitlines()
        return f"rerun exit {exc.returncode}: {lines[-1][:300] if lines else ''}"
    return str(exc)


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


@dataclass
class Outcome:
    """How a supervised run ended: `phalanx up`'s exit code, the world's own, and every
    ending that was not asked for ("agent r2: killed by SIGKILL after 6.1 s"), in order.
    """

    code: int
    world_code: int | None
    problems: list[str] = field(default_factory=list)

    @property
    def complete(self) -> bool:
        """Whether the run ended as asked: the world finished and nothing died."""
        return self.code == EXIT_FINISHED


def supervise(children: list[Child], options: UpOptions, stop: Stoppable) -> Outcome:
    """Run until the world ends (or the timeout, or `stop`); the outcome."""
    for child in children:
        child.start()
    world, agents = children[0], children[1:]
    started = time.monotonic()
    deadline = started + options.timeout_s
    problems: list[str] = []
    world_code: int | None = None
    try:
        while not stop.is_set() and time.monotonic() < deadline:
            world_code = world.poll()
            if world_code is not None:
                break
            for agent in agents:
                _check_agent(agent, options, problems, started)
            if _robots_gone(agents, problems, started):
                break
            time.sleep(0.1)
        else:
            why = "interrupted" if stop.is_set() else f"timed out after {options.timeout_s:g} s"
            log.error("stopping the fleet: %s", why)
            problems.append(why)
    finally:
        stop_all(children)
    if world_code is not None and world_code not in (EXIT_FINISHED, EXIT_INCOMPLETE):
        why = agent_exit_reason(world_code)
        problems.insert(0, f"world: {why} after {_since(world, started)}")
    if problems:
        log.error("the run did not end as asked: %s", "; ".join(problems))
    return Outcome(EXIT_FAILED if problems else EXIT_FINISHED, world_code, problems)


def _robots_gone(children: list[Child], problems: list[str], started: float) -> bool:
    """Whether a simulator of the run's robots has ended (whatever its exit code, the
    robots are gone with it: the run stops, its record kept as far as it went).
    """
    for child in children:
        code = child.poll() if child.kind == "simulator" else None
        if code is not None:
            if code == 0:  # (a failure was reported with the other endings already)
                problems.append(f"simulator {child.name}: ended after {_since(child, started)}")
            log.error("the robots' simulator %s ended: stopping the fleet", child.name)
            return True
    return False


def _since(child: Child, started: float) -> str:
    return f"{time.monotonic() - started:.1f} s"


def _check_agent(agent: Child, options: UpOptions, problems: list[str], started: float) -> None:
    code = agent.poll()
    if code is None or agent.reported:
        return
    agent.reported = True
    if code == 0:
        return
    agent.exits.append(code)
    problem = f"{agent.kind} {agent.name}: {agent_exit_reason(code)} after {_since(agent, started)}"
    log.error("%s", problem)
    if options.restart and agent.restarts < options.max_restarts:
        agent.restarts += 1
        problem += f" (restarted, restart {agent.restarts})"
        time.sleep(min(2.0, 0.2 * 2**agent.restarts))
        log.warning("restarting agent %s (restart %d)", agent.name, agent.restarts)
        agent.start()
    problems.append(problem)
