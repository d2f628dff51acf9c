"""Every process's receiving side, in this process, for the fuzzers: the real agent
runtime, world process, host daemon and launcher watch, wired to a loopback session
that hands an injected payload to whatever the process subscribed to that key, through
the same decoding and checks (`phalanx.wire.transport.deliver`, polled rings) as Zenoh
would. After payloads, the process keeps working: the agent steps on the world's next
frame, the world ticks and writes its run's log and metrics, and the checks say what a
crash or an unsafe command looks like.
"""

from __future__ import annotations

import fnmatch
import json
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_robot, load_scenario
from phalanx.core.limits import run_limits
from phalanx.runtime.clock import Tick
from phalanx.wire.codec import DecodeStats, encode
from phalanx.wire.delivery import Polled, deliver
from phalanx.wire.keys import leader_key, robot_key
from phalanx.wire.messages import (
    AgentEvent,
    AgentReport,
    LeaderAnnouncement,
    Message,
    OperatorCommand,
    RobotFlags,
    RobotState,
    ScanMessage,
    SenseFrame,
    VelocityCommand,
)

WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
NAV_WEDGE = CONFIG_ROOT / "scenarios" / "nav_corridor_wedge3.toml"  # a fleet that maps
REAL = CONFIG_ROOT / "scenarios" / "real_wedge.toml"
FLEET = "fuzz"


@dataclass
class _Sample:
    key_expr: str
    payload: Any


@dataclass
class _Bytes:
    raw: bytes

    def to_bytes(self) -> bytes:
        return self.raw


@dataclass
class LoopbackSession:
    """What a process declares on its session, served in-process: `inject` hands a
    payload to every subscription whose key expression matches. Rate limits are not
    applied: every payload reaches the decoder (tests/faults/test_flood_limit.py tests
    the limits on real sessions)."""

    stats: DecodeStats = field(default_factory=DecodeStats)
    subscriptions: list[tuple[str, Callable[[str, bytes], None]]] = field(default_factory=list)
    published: int = 0
    relinks: int = 0  # (never re-opened: nothing to lose)

    def subscribe(
        self,
        key_expr: str,
        model: type,
        on_message: Callable[..., None],
        *,
        context: Any = None,
        rate_hz: float | None = None,
    ) -> None:
        def handler(key: str, payload: bytes) -> None:
            deliver(key, payload, model, self.stats, on_message, context)

        self.subscriptions.append((key_expr, handler))

    def subscribe_polled(
        self,
        key_expr: str,
        model: type,
        capacity: int,
        *,
        context: Any = None,
        rate_hz: float | None = None,
    ) -> Polled[Any]:
        ring: Polled[Any] = Polled(model, self.stats, capacity, context)

        def put(key: str, payload: bytes) -> None:
            ring.put(_Sample(key, _Bytes(payload)))

        self.subscriptions.append((key_expr, put))
        return ring

    def inject(self, key: str, payload: bytes) -> int:
        """Deliver `payload` as if it arrived on `key`; how many subscriptions took it."""
        taken = 0
        for pattern, handler in list(self.subscriptions):
            if _matches(pattern, key):
                handler(key, payload)
                taken += 1
        return taken

    def publish(self, key: str, message: Message, *, reliable_block: bool = False) -> None:
        encode(message)  # what the real session does first: it must not fail
        self.published += 1

    def declare_alive(self, key: str) -> None:
        """Nothing to hold in-process."""

    def watch_alive(self, key_expr: str, on_change: Callable[[str, bool], None]) -> None:
        """No other process comes or goes in-process."""

    def serve_status(self, key: str, status: Callable[[], dict[str, Any]]) -> None:
        self.status = status


def _matches(pattern: str, key: str) -> bool:
    parts, keys = pattern.split("/"), key.split("/")
    return len(parts) == len(keys) and all(
        p == k or (p == "*" and k) or fnmatch.fnmatchcase(k, p)
        for p, k in zip(parts, keys, strict=True)
    )


def _held_to_limits(commands: list[tuple[float, float]], limits: Any) -> None:
    """Every command finite and within the run's limits (m/s, rad/s)."""
    for v, w in commands:
        assert math.isfinite(v), v
        assert math.isfinite(w), w
        assert abs(v) <= limits.v_max_mps + 1e-9, v
        assert abs(w) <= limits.omega_max_radps + 1e-9, w


def _agent_checked(commands: list[tuple[float, float]], limits: Any, session: Any) -> None:
    """An agent under test so far: its commands held to the run's limits (then
    forgotten), its status serialisable, no handler error.
    """
    _held_to_limits(commands, limits)
    commands.clear()
    json.dumps(session.status())
    assert not session.stats.handler_errors, session.stats.last_error


class _Stop:
    """Never set: wait for the next frame."""

    def is_set(self) -> bool:
        return False

    def wait(self, timeout: float | None = None) -> bool:
        return False


# --- an agent ----------------------------------------------------------------------------


def _leader_silent(k: int) -> bool:
    """Whether r1 says nothing at tick `k`: now and then the leader goes silent."""
    return (k // 40) % 4 == 3


class AgentUnderTest:
    """Robot r2's agent process (realtime: flags and path states through rings; or
    lockstep: every state in the world's frames), stepping on frames this harness sends."""

    def __init__(self, *, clock: str = "realtime", navigating: bool = False) -> None:
        from phalanx.runtime.agent import AgentRuntime, RuntimeOptions
        from phalanx.runtime.robot_io import WorldLink
        from phalanx.wire.bounds import FleetBounds
        from phalanx.wire.transport import TransportConfig

        # A day: longer than any campaign's steps (the frames of a run's end are refused).
        # Navigating: every robot's scans feed its copy of the fleet's map.
        path = NAV_WEDGE if navigating else WEDGE
        self.scenario = apply_overrides(load_scenario(path), ["duration_s=86400"])
        self.robot = load_robot(self.scenario.robot)
        self.limits = run_limits(self.robot, self.scenario.limits)
        bounds = FleetBounds.of(self.scenario, self.robot)
        options = RuntimeOptions(
            fleet=FLEET,
            transport=TransportConfig(),
            clock=clock,  # type: ignore[arg-type]
        )
        self.link = WorldLink(FLEET, "r2", frame_timeout_s=5.0, bounds=bounds)
        self.runtime = AgentRuntime(
            "r2", self.scenario, self.robot, options, clock=self.link, io=self.link
        )
        self.session = LoopbackSession()
        self.runtime._session = self.session  # type: ignore[assignment]
        self.runtime._wire(self.session)  # type: ignore[arg-type]
        self.lockstep = clock == "lockstep"
        self.k = 0
        self.steps = 0
        self.commands: list[tuple[float, float]] = []

    @property
    def t_s(self) -> float:
        return self.k * self.scenario.dt_s

    def keys(self) -> dict[str, tuple[type[Message], str, Callable[[], list[bytes]]]]:
        """Every key the agent subscribes to: (model, key, a few valid payloads now)."""
        return {
            "agent/flags": (RobotFlags, robot_key(FLEET, "r1", "flags"), self._valid_flags),
            "agent/state": (RobotState, robot_key(FLEET, "r1", "state"), self._valid_state),
            "agent/sense": (SenseFrame, robot_key(FLEET, "r2", "sense"), self._valid_frame),
            "agent/scan": (ScanMessage, robot_key(FLEET, "r1", "scan"), self._valid_scan),
            "agent/operator": (
                OperatorCommand,
                robot_key(FLEET, "r2", "operator"),
                self._valid_operator,
            ),
        }

    def _valid_operator(self) -> list[Message]:
        """An operator's twist, and a goal, for r2 (which leads while r1 is silent)."""
        stamp = 1.8e9 + self.t_s
        return [
            OperatorCommand(robot_id="r2", stamp_s=stamp, twist=True, v_mps=0.2, omega_radps=0.3),
            OperatorCommand(robot_id="r2", stamp_s=stamp, goal=True, goal_x_m=3.0, goal_y_m=1.0),
        ]

    def _valid_scan(self) -> list[Message]:
        t = self.t_s
        return [
            ScanMessage(
                robot_id="r1", stamp_s=t, x_m=0.15 * t, y_m=0.0, theta_rad=0.0,
                ranges_m=(2.0,) * 8 + (5.0,) * 8, echo=(True,) * 8 + (False,) * 8,
            )
        ]  # fmt: skip

    def _peer_state(self, rid: str, t_s: float) -> RobotState:
        x = 0.15 * t_s if rid == "r1" else 0.15 * t_s - 0.7
        y = {"r1": 0.0, "r2": 0.7, "r3": -0.7}[rid]
        return RobotState(
            robot_id=rid,
            seq=self.k + 1,
            stamp_s=t_s,
            x_m=x,
            y_m=y,
            theta_rad=0.0,
            v_mps=0.15,
            omega_radps=0.0,
            fsm_state="NAVIGATE" if rid == "r1" else "FORMATION_TRACK",
            leader_id="" if rid == "r1" else "r1",
            formation_leader_id="r1",
            clear=True,
        )

    def _valid_state(self) -> list[Message]:
        return [self._peer_state("r1", self.t_s), self._peer_state("r1", self.t_s + 0.1)]

    def _valid_flags(self) -> list[Message]:
        return [m.flags() for m in self._valid_state()]  # type: ignore[attr-defined]

    def _frame(self, k: int, *, final: bool = False) -> SenseFrame:
        t = k * self.scenario.dt_s
        return SenseFrame(
            robot_id="r2",
            tick=k,
            t_s=t,
            dt_s=self.scenario.dt_s,
            x_m=0.15 * t - 0.7,
            y_m=0.7,
            theta_rad=0.0,
            v_mps=0.1,
            omega_radps=0.0,
            sonar_ranges_m=(5.0,) * 16,
            bumpers=(False,) * 10,
            final=final,
            peers=self._relayed(t) if self.lockstep else (),
        )

    def _relayed(self, t_s: float) -> tuple[RobotState, ...]:
        """What the world's frame at `t_s` carries: r1's and r3's states of the tick before
        (none from the leader while it is silent, none at the run's start)."""
        before = t_s - self.scenario.dt_s
        peers = ("r3",) if _leader_silent(round(t_s / self.scenario.dt_s)) else ("r1", "r3")
        return tuple(self._peer_state(r, before) for r in peers) if before >= 0 else ()

    def _valid_frame(self) -> list[Message]:
        return [self._frame(self.k + 1), self._frame(self.k + 2)]

    def inject(self, key: str, payload: bytes) -> None:
        """A payload arrives on `key`."""
        self.session.inject(key, payload)

    def step(self) -> None:
        """A fuzzed frame the gate takes is stepped on (one that ends the run fails);
        then the fleet's next tick: r1 and r3 publish, the world sends r2's frame, r2
        steps on whichever frame its gate takes."""
        frame = self.link.gate.offer(self.link._box.take(0.0))  # what next_tick does
        if self.link.gate.ended():
            raise AssertionError(f"agent ended its run at tick {self.k} ({self.link.ending})")
        if frame is not None:
            self.link._frame = self.link._relay_from = frame  # (its states heard too)
            self._step_on(Tick(frame.tick, frame.t_s))
        gate_tick = self.link.gate._tick  # a fuzzed frame the gate took moves the clock on
        self.k = max(self.k, gate_tick if gate_tick is not None else 0) + 1
        for rid in ("r1", "r3"):
            if rid == "r1" and _leader_silent(self.k):
                continue  # now and then the leader goes silent: followers hold, then elect
            state = self._peer_state(rid, self.t_s - self.scenario.dt_s)
            self.session.inject(robot_key(FLEET, rid, "state"), encode(state))
            self.session.inject(robot_key(FLEET, rid, "flags"), encode(state.flags()))
        self.session.inject(robot_key(FLEET, "r2", "sense"), encode(self._frame(self.k)))
        tick = self.runtime.clock.next_tick(_Stop())
        if tick is None:  # the gate ended the run: a fuzzed final frame it believed
            raise AssertionError(f"agent ended its run at tick {self.k} ({self.link.ending})")
        self._step_on(tick)

    def _step_on(self, tick: Any) -> None:
        self.k = max(self.k, tick.k)
        observation = self.runtime.io.read(tick)
        assert observation is not None, "the frame the gate chose was not read"
        out = self.runtime.step(tick, observation)
        self.steps += 1
        self.commands.append((out.command.v_mps, out.command.omega_radps))

    def check(self) -> None:
        """The commands stayed finite and within the run's limits; status serialises."""
        _agent_checked(self.commands, self.limits, self.session)
        assert not self.runtime.unsent, "an own message could not be sent"


class DriverAgentUnderTest:
    """Robot r2's agent on a driver (the simulated robot behind the safety layer), with
    real_wedge's estimator: it hears its positioning sources (`fix`, `relative`: motion
    capture, the world's simulated camera) and fuses what they say at every step."""

    EPOCH_S = 1.8e9  # the fleet's epoch in Unix time: fixes are stamped in Unix time

    def __init__(self) -> None:
        from phalanx.core.limits import safety_limits
        from phalanx.drivers.safety import SafeDriver
        from phalanx.drivers.sim import SimDriver
        from phalanx.runtime.agent import AgentRuntime, RuntimeOptions
        from phalanx.runtime.clock import EpochClock
        from phalanx.runtime.positioning import PositioningInbox
        from phalanx.runtime.robot_io import DriverIO
        from phalanx.wire.transport import TransportConfig

        self.scenario = apply_overrides(load_scenario(REAL), ["duration_s=86400"])
        self.robot = load_robot(self.scenario.robot)
        self.limits = run_limits(self.robot, self.scenario.limits)
        limits = safety_limits(self.robot, self.scenario.limits)
        self.safe = SafeDriver(SimDriver(self.robot), limits)
        self.safe.connect()
        self.inbox = PositioningInbox(FLEET, "r2", epoch_s=self.EPOCH_S)
        io = DriverIO(
            self.safe, self.robot, origin=self.scenario.start_pose("r2"), positioning=self.inbox
        )
        options = RuntimeOptions(fleet=FLEET, transport=TransportConfig(), clock="realtime")
        clock = EpochClock(epoch_s=self.EPOCH_S, dt_s=self.scenario.dt_s, steps=10**9)
        self.runtime = AgentRuntime("r2", self.scenario, self.robot, options, clock=clock, io=io)
        self.session = LoopbackSession()
        self.runtime._session = self.session  # type: ignore[assignment]
        self.runtime._wire(self.session)  # type: ignore[arg-type]
        self.k = 0
        self.steps = 0
        self.commands: list[tuple[float, float]] = []

    def keys(self) -> dict[str, tuple[type[Message], str, Callable[[], list[bytes]]]]:
        """The positioning keys of a robot on a driver."""
        from phalanx.wire.positions import PoseFixMessage, RelativeFixMessage

        def valid_fix() -> list[Message]:
            stamp = self.EPOCH_S + self.k * self.scenario.dt_s
            pose = self.scenario.start_pose("r2")
            return [
                PoseFixMessage(
                    robot_id="r2", stamp_s=stamp, x_m=pose.x_m, y_m=pose.y_m,
                    theta_rad=pose.theta_rad, std_m=0.002, std_rad=0.002,
                )
            ]  # fmt: skip

        def valid_relative() -> list[Message]:
            stamp = self.EPOCH_S + self.k * self.scenario.dt_s
            return [
                RelativeFixMessage(
                    robot_id="r2", target_id="r1", stamp_s=stamp, range_m=1.0,
                    bearing_rad=-0.78, std_range_m=0.02, std_bearing_rad=0.02,
                )
            ]  # fmt: skip

        return {
            "agent/fix": (PoseFixMessage, robot_key(FLEET, "r2", "fix"), valid_fix),
            "agent/relative": (
                RelativeFixMessage,
                robot_key(FLEET, "r2", "relative"),
                valid_relative,
            ),
        }

    def inject(self, key: str, payload: bytes) -> None:
        """A payload arrives on `key`."""
        self.session.inject(key, payload)

    def step(self) -> None:
        """A control step on what the robot and its positioning sources said."""
        self.k += 1
        tick = Tick(self.k, self.k * self.scenario.dt_s)
        observation = self.runtime.io.read(tick)
        assert observation is not None, "the simulated robot gave no reading"
        out = self.runtime.step(tick, observation)
        self.runtime.io.write(tick, out.command)
        self.steps += 1
        self.commands.append((out.command.v_mps, out.command.omega_radps))

    def check(self) -> None:
        """Commands finite and within the run's limits; status serialises."""
        _agent_checked(self.commands, self.limits, self.session)

    def close(self) -> None:
        """Stop the simulated robot's thread."""
        self.safe.close()


# --- the world ---------------------------------------------------------------------------


class WorldUnderTest:
    """The world process of the wedge: it takes payloads, ticks, and writes its log (in
    lockstep; in real time, the only world that hears commands)."""

    def __init__(self, clock: str = "lockstep", *, observed: tuple[str, ...] = ()) -> None:
        from phalanx.runtime.world_process import WorldOptions, WorldProcess
        from phalanx.wire.transport import TransportConfig

        scenario = apply_overrides(load_scenario(WEDGE), ["duration_s=600"])
        self.robot = load_robot(scenario.robot)
        self.EPOCH_S = time.time()  # (a robot's poses are kept only if stamped near now)
        options = WorldOptions(
            fleet=FLEET, transport=TransportConfig(), tick_timeout_s=0.0,
            clock=clock,  # type: ignore[arg-type]
            observed=observed, epoch_s=self.EPOCH_S if observed else None,
        )  # fmt: skip
        self.world = WorldProcess(scenario, self.robot, options)
        self.session = LoopbackSession()
        self.world._wire(self.session)  # type: ignore[arg-type]
        self.k = 0

    def keys(self) -> dict[str, tuple[type[Message], str, Callable[[], list[bytes]]]]:
        """Every key the world subscribes to."""
        t = self.k * 0.1
        cmd = VelocityCommand(robot_id="r2", tick=self.k, stamp_s=t, v_mps=0.1, omega_radps=0.0)
        state = RobotState(
            robot_id="r2",
            seq=1,
            stamp_s=t,
            x_m=0.0,
            y_m=0.0,
            theta_rad=0.0,
            v_mps=0.1,
            omega_radps=0.0,
            fsm_state="FORMATION_TRACK",
        )
        event = AgentEvent(
            robot_id="r2", t_s=t, source="HOLD", target="FORMATION_TRACK", reason="x"
        )
        report = AgentReport(
            robot_id="r2",
            steps=self.k,
            saturations=0,
            accel_limited=0,
            dropped_messages=0,
            late_peer_steps=0,
        )
        leader = LeaderAnnouncement(leader_id="r2", epoch=1, stamp_s=t, previous_id="r1")

        def both(message: Message) -> Callable[[], list[Message]]:
            return lambda: [message]

        from phalanx.wire.positions import PoseFixMessage, TruthMessage

        truth = TruthMessage(
            robot_id="r2", stamp_s=time.time(), x_m=0.1 * t, y_m=0.7, theta_rad=0.0,
            v_mps=0.1, omega_radps=0.0, source="AMRISim SIMSTAT",
        )  # fmt: skip
        fix = PoseFixMessage(
            robot_id="r3", stamp_s=time.time(), x_m=0.1 * t, y_m=-0.7, theta_rad=0.0,
            std_m=0.002, std_rad=0.002,
        )  # fmt: skip
        return {
            "world/truth": (TruthMessage, robot_key(FLEET, "r2", "truth"), both(truth)),
            "world/fix": (PoseFixMessage, robot_key(FLEET, "r3", "fix"), both(fix)),
            "world/cmd": (VelocityCommand, robot_key(FLEET, "r2", "cmd"), both(cmd)),
            "world/state": (RobotState, robot_key(FLEET, "r2", "state"), both(state)),
            "world/event": (AgentEvent, robot_key(FLEET, "r2", "event"), both(event)),
            "world/report": (AgentReport, robot_key(FLEET, "r2", "report"), both(report)),
            "world/leader": (LeaderAnnouncement, leader_key(FLEET), both(leader)),
        }

    def inject(self, key: str, payload: bytes) -> None:
        """A payload arrives on `key`."""
        self.session.inject(key, payload)

    def step(self) -> None:
        """One tick of the world (with nobody alive: no waiting)."""
        if self.k < self.world.steps:
            self.world._tick(self.session, self.k)  # type: ignore[arg-type]
            self.k += 1

    def check(self) -> None:
        """The run's log and metrics can be written from what it took; status serialises."""
        from phalanx.analysis.metrics import run_metrics
        from phalanx.analysis.results import _finite

        log = self.world._log()
        metrics = run_metrics(log)
        metrics["runtime"] = log.runtime
        json.dumps(_finite(metrics))
        json.dumps(self.session.status())
        assert not self.session.stats.handler_errors, self.session.stats.last_error
        assert set(log.runtime["agents"]) <= {"r1", "r2", "r3"}  # type: ignore[arg-type]
        for entry in log.runtime["leadership"]:  # type: ignore[union-attr]
            assert entry["leader_id"] in ("r1", "r2", "r3")


# --- a host daemon and the launcher ---------------------------------------------------------


class DaemonUnderTest:
    """A host daemon of the loopback deployment answering requests (it spawns nothing:
    no payload can carry the deployment's digest)."""

    def __init__(self, workdir: Path) -> None:
        from phalanx.hosts.daemon import DaemonOptions, HostDaemon
        from phalanx.hosts.deployment import load_deployment

        self.daemon = HostDaemon(
            load_deployment("loopback"), "robot-b", DaemonOptions(workdir=workdir, echo=False)
        )
        self.lock = threading.Lock()

    def keys(self) -> dict[str, tuple[type[Any], str, Callable[[], list[bytes]]]]:
        """The daemon's queryables: spawn, stop, status."""
        from phalanx.hosts.protocol import SpawnRequest, StopRequest

        spawn = SpawnRequest(deployment="loopback", digest="0" * 64, run_id="run-1")
        stop = StopRequest(deployment="loopback", digest="0" * 64, run_id="run-1")
        return {
            "daemon/spawn": (SpawnRequest, "spawn", lambda: [spawn]),
            "daemon/stop": (StopRequest, "stop", lambda: [stop]),
            "daemon/status": (StopRequest, "status", lambda: [stop]),
        }

    def inject(self, topic: str, payload: bytes) -> None:
        """A request arrives: its reply must be a valid HostReply; nothing is started."""
        from phalanx.hosts.protocol import HostReply

        reply = HostReply.model_validate_json(self.daemon.answer(topic, payload))
        assert not self.daemon.children, "a fuzzed request started a process"
        assert reply.status.host == "robot-b"

    def step(self) -> None:
        """The daemon's supervision tick."""
        self.daemon.supervise()

    def check(self) -> None:
        """Its status still serialises."""
        self.daemon.status().model_dump_json()


class LauncherUnderTest:
    """What `phalanx launch` and `phalanx status` hear: states, log lines, host replies."""

    def __init__(self) -> None:
        from phalanx.hosts.fleet_client import FleetWatch
        from phalanx.wire.bounds import FleetBounds

        scenario = load_scenario(WEDGE)
        self.watch = FleetWatch()
        self.session = LoopbackSession()
        self.session.subscribe(
            "phalanx/fuzz/robot/*/state",
            RobotState,
            self.watch.on_state,
            context=FleetBounds.of(scenario, load_robot(scenario.robot)),
        )

    def keys(self) -> dict[str, tuple[type[Any], str, Callable[[], list[bytes]]]]:
        """The state watch, log lines and replies of host daemons."""
        from phalanx.hosts.protocol import HostReply, HostStatus, LogLine

        state = RobotState(
            robot_id="r2",
            seq=1,
            stamp_s=1.0,
            x_m=0.0,
            y_m=0.0,
            theta_rad=0.0,
            v_mps=0.1,
            omega_radps=0.0,
            fsm_state="FORMATION_TRACK",
        )
        line = LogLine(host="robot-a", child="r1", run_id="x", time_unix=1.0, line="hello")
        status = HostStatus(
            host="robot-a",
            fleet="loopback",
            deployment="loopback",
            digest="0" * 64,
            time_unix=1.0,
            uptime_s=1.0,
        )
        reply = HostReply(ok=True, status=status)
        return {
            "launcher/state": (RobotState, robot_key(FLEET, "r2", "state"), lambda: [state]),
            "launcher/log": (LogLine, "phalanx/fuzz/host/robot-a/log/r1", lambda: [line]),
            "launcher/reply": (HostReply, "reply", lambda: [reply]),
        }

    def inject(self, key: str, payload: bytes) -> None:
        """A payload arrives (state, log line, or a host's reply to a request)."""
        from phalanx.hosts.fleet_client import _first_reply

        if "/log/" in key:
            self.watch.on_log(_Sample(key, _Bytes(payload)))
        elif key == "reply":
            _first_reply([_Reply(_Sample("k", _Bytes(payload)))])
        else:
            self.session.inject(key, payload)

    def step(self) -> None:
        """The launcher's table."""
        for rid in ("r1", "r2", "r3"):
            self.watch.state(rid)
            self.watch.rate_hz(rid, 0.0)

    def check(self) -> None:
        """Only the fleet's robots were ever shown."""
        assert set(self.watch.states) <= {"r1", "r2", "r3"}
        assert not self.session.stats.handler_errors, self.session.stats.last_error


@dataclass
class _Reply:
    ok: Any


def receivers(workdir: Path) -> list[Any]:
    """One of each receiving process."""
    return [AgentUnderTest(), WorldUnderTest(), DaemonUnderTest(workdir), LauncherUnderTest()]


def sweep(receiver: Any, key: str, *, check_every: int = 200) -> int:
    """Every field of `key`'s message at each boundary value of its type, one at a time,
    set on a valid message of the moment (`wirefuzz.boundary_sweep`), each followed by a
    step; how many were sent."""
    from wirefuzz import boundary_sweep, swept

    model, wire_key, valid = receiver.keys()[key]
    cases = boundary_sweep(model)
    for i, (name, value, form) in enumerate(cases, 1):
        payload = swept(valid()[0], name, value, form)
        try:
            receiver.inject(wire_key, payload)
            receiver.step()
            if i % check_every == 0:
                receiver.check()
        except Exception as exc:
            raise AssertionError(f"{key}: {name}={value!r} ({form}) -> {exc!r}") from exc
    receiver.check()
    return len(cases)


def campaign(receiver: Any, key: str, n: int, *, seed: int, check_every: int = 200) -> int:
    """`n` hostile payloads (`lab/wirefuzz.py`) on `key` of `receiver`, each
    followed by a step of it, checked every `check_every`; how many were sent. Raises on
    the first crash or unsafe command (the failing payload in the message)."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import seed as hypothesis_seed
    from wirefuzz import hostile_payloads

    model, wire_key, valid = receiver.keys()[key]
    sent = [0]

    @hypothesis_seed(seed)
    @settings(
        max_examples=n,
        database=None,
        deadline=None,
        phases=_GENERATE,
        suppress_health_check=list(HealthCheck),
    )
    @given(hostile_payloads(model, valid))
    def one(payload: bytes) -> None:
        try:
            receiver.inject(wire_key, payload)
            receiver.step()
            sent[0] += 1
            if sent[0] % check_every == 0:
                receiver.check()
        except Exception as exc:
            raise AssertionError(f"{key}: payload {payload[:300]!r} -> {exc!r}") from exc

    one()
    receiver.check()
    return sent[0]


def _phases() -> tuple[Any, ...]:
    from hypothesis import Phase

    return (Phase.generate,)  # no shrinking: the failing payload is in the message


_GENERATE = _phases()
