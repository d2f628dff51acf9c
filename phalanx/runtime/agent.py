"""The agent process: Zenoh in, the agent core's step, the command out, telemetry.

With the `sim` driver the world drives the clock: each SenseFrame is a tick, answered
with a VelocityCommand for the same tick. In lockstep the agent first waits (bounded)
for the peer states the batch runner would give it (published `comm_delay_s` earlier),
which is what makes a multi-process run reproduce the in-process one.

What a robot hears: every robot's small `RobotFlags` (leadership and deadlock are
decided from them on every robot), and the full `RobotState` only of the robots it may
track: those on its follow-tree path to the current leader, subscribed to as the
leadership changes. Leader-state traffic so stays O(followers of each robot). In
lockstep (one machine, deterministic runs) it takes every robot's state instead, so the
robot it tracks after a leadership change has a state from the very same tick. A robot
that takes the lead announces it on `phalanx/<fleet>/leader`. A robot started while its
fleet is already running (its first tick is not 0) joins: it stays still until it has
heard the fleet's leader and epoch.
"""

from __future__ import annotations

import logging
import queue
import time
from dataclasses import dataclass
from typing import Literal, TypeVar

from phalanx.agents.agent import Agent, Observation, StepOutput
from phalanx.core.config import RobotParams, Scenario
from phalanx.core.formation import Formation, scenario_formation
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.rigid_body import live_errors
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.runtime.signals import Stoppable
from phalanx.telemetry.stream import Telemetry, sonar_rays
from phalanx.wire.keys import alive_key, leader_key, robot_key, robot_of, robots_key, status_key
from phalanx.wire.messages import (
    AgentEvent,
    AgentReport,
    LeaderAnnouncement,
    RobotFlags,
    RobotState,
    SenseFrame,
    VelocityCommand,
)
from phalanx.wire.transport import FleetSession, History, Polled, TransportConfig, open_session

log = logging.getLogger("phalanx.agent")
ClockMode = Literal["lockstep", "realtime"]
EPS_S = 1e-6
# Flags (or states) held per robot between two steps before the oldest are dropped (one
# arrives per robot and control period; the ring absorbs a late step).
FLAGS_RING_PER_ROBOT = 8
# Unchanged flags go out at least this often (and three times per leader timeout).
FLAGS_HEARTBEAT_S = 0.2
REPORT_FLUSH_S = 2.0  # how long the final report waits for telemetry to go out
S = TypeVar("S", RobotState, RobotFlags)


def pick_state(states: list[S], not_after_s: float) -> S | None:
    """The newest state stamped no later than `not_after_s`."""
    chosen = None
    for state in states:
        if state.stamp_s <= not_after_s + EPS_S and (
            chosen is None or state.stamp_s > chosen.stamp_s
        ):
            chosen = state
    return chosen


# What flags say, as far as other robots decide on it: not who sent them, their sequence
# number or stamp, nor a follower's copy of the leader's profile clock (only the leader's
# is read).
_FLAGS_VOLATILE = frozenset({"version", "robot_id", "seq", "stamp_s", "profile_s"})
_FLAGS_DECISIVE = tuple(f for f in RobotFlags.model_fields if f not in _FLAGS_VOLATILE)


class FlagsThrottle:
    """Decides which flags go out: those that say something new, and unchanged ones as a
    heartbeat every `heartbeat_s` (every robot hears every robot: unchanged flags at
    every step would cost the fleet n^2 messages a period for nothing).
    """

    def __init__(self, heartbeat_s: float) -> None:
        self.heartbeat_s = heartbeat_s
        self.skipped = 0
        self._sent: tuple[float, tuple[object, ...]] | None = None  # when, what

    def due(self, flags: RobotFlags) -> bool:
        """Whether to publish `flags` (if so, they count as sent)."""
        content = tuple(getattr(flags, f) for f in _FLAGS_DECISIVE)
        if flags.formation_leader_id == flags.robot_id:
            content += (flags.profile_s,)
        sent = self._sent
        if (
            sent is None
            or content != sent[1]
            or flags.stamp_s - sent[0] >= self.heartbeat_s - EPS_S
        ):
            self._sent = (flags.stamp_s, content)
            return True
        self.skipped += 1
        return False


@dataclass
class RuntimeOptions:
    """How an agent process runs."""

    fleet: str
    transport: TransportConfig
    clock: ClockMode = "lockstep"
    peer_wait_s: float = 2.0
    frame_timeout_s: float = 30.0


class AgentRuntime:
    """One robot's process loop around an `Agent`."""

    publish_commands = True  # the world executes them (sim driver)

    def __init__(
        self,
        robot_id: str,
        scenario: Scenario,
        robot: RobotParams,
        options: RuntimeOptions,
        *,
        telemetry: Telemetry | None = None,
    ) -> None:
        self.robot_id = robot_id
        self.scenario = scenario
        self.options = options
        self.formation: Formation = scenario_formation(scenario)
        self.agent = Agent(robot_id, scenario=scenario, robot=robot, formation=self.formation)
        self.robot = robot
        self._last_peers: dict[str, RobotState] = {}
        self.step_times_s: list[float] = []
        self.telemetry = telemetry
        self.peers = History(depth=16)
        self.flags = History(depth=4)  # one a period per robot; real time needs the newest
        self.frames: queue.Queue[SenseFrame] = queue.Queue()
        self.dead: set[str] = set()
        self.steps = 0
        self.late_peer_steps = 0
        self.announcements: list[LeaderAnnouncement] = []
        self._subscribed: set[str] = set()
        self._session: FleetSession | None = None
        self.world_lost = False  # ended because the world's frames stopped coming
        self._flag_ring: Polled[RobotFlags] | None = None
        self._state_rings: list[Polled[RobotState]] = []
        self.flags_out = FlagsThrottle(min(FLAGS_HEARTBEAT_S, scenario.leader_timeout_s / 3))

    @property
    def lockstep(self) -> bool:
        """Whether the fleet runs in lockstep (deterministic, one machine)."""
        return self.options.clock == "lockstep"

    @property
    def watched(self) -> tuple[str, ...]:
        """Robots whose full state this one needs: everyone in lockstep; else those on
        its follow-tree path to the leader (any of them may become the one it tracks).
        """
        others = tuple(r for r in self.formation.robot_ids if r != self.robot_id)
        if self.lockstep:
            return others
        leader = self.agent.leadership.leader_id
        if leader == self.robot_id:
            return ()
        return self.agent.leadership.path(self.robot_id)

    def run(self, stop: Stoppable) -> AgentReport:
        """Serve ticks until the world's final frame, `stop`, or no frame for a while."""
        fleet = self.options.fleet
        with open_session(self.options.transport) as session:
            self._session = session
            self._wire(session)
            self._loop(stop)
            report = self._report()
            session.publish(robot_key(fleet, self.robot_id, "report"), report, reliable_block=True)
            time.sleep(0.05)  # let the last puts leave before the session closes
        return report

    def _wire(self, session: FleetSession) -> None:
        fleet, rid = self.options.fleet, self.robot_id
        session.declare_alive(alive_key(fleet, rid))
        if self.publish_commands:  # a simulated robot: the world's frames are its ticks
            session.subscribe(
                robot_key(fleet, rid, "sense"), SenseFrame, lambda _k, f: self.frames.put(f)
            )
        if self.lockstep:  # every state (they carry the flags): as the batch runner has them
            session.subscribe(robots_key(fleet, "state"), RobotState, self._on_state)
        else:
            # Every robot hears every robot: drained once per step, not a wake-up each.
            capacity = FLAGS_RING_PER_ROBOT * len(self.formation.robot_ids)
            self._flag_ring = session.subscribe_polled(
                robots_key(fleet, "flags"), RobotFlags, capacity
            )
            self._follow_path()
        session.subscribe(leader_key(fleet), LeaderAnnouncement, self._on_announcement)
        session.watch_alive(f"phalanx/{fleet}/alive/*", self._on_alive)
        session.serve_status(status_key(fleet, rid), self._status)

    def _on_state(self, key: str, state: RobotState) -> None:
        if robot_of(key) == state.robot_id and state.robot_id not in self.dead:
            self.peers.push(state.robot_id, state)

    def _on_flags(self, key: str, flags: RobotFlags) -> None:
        if robot_of(key) == flags.robot_id and flags.robot_id not in self.dead:
            self.flags.push(flags.robot_id, flags)

    def _on_announcement(self, _key: str, message: LeaderAnnouncement) -> None:
        self.announcements.append(message)  # a record: the flags carry the decision

    def _follow_path(self) -> None:
        """Subscribe to the states of robots on the path to the leader not yet heard."""
        if self._session is None:
            return
        for peer in self.watched:
            if peer not in self._subscribed:
                self._subscribed.add(peer)
                key = robot_key(self.options.fleet, peer, "state")
                ring = self._session.subscribe_polled(key, RobotState, FLAGS_RING_PER_ROBOT)
                self._state_rings.append(ring)

    def _on_alive(self, key: str, alive: bool) -> None:
        robot = key.rsplit("/", 1)[-1]
        if robot == self.robot_id or robot not in self.formation.positions:
            return
        if alive:
            self.dead.discard(robot)
        else:
            self.dead.add(robot)
            self.peers.forget(robot)
            self.flags.forget(robot)

    def _status(self) -> dict[str, object]:
        stats = self._session.stats.as_dict() if self._session else {}
        return {
            "robot_id": self.robot_id,
            "steps": self.steps,
            "state": self.agent.state_name,
            "leader": self.agent.leadership.leader_id,
            "epoch": self.agent.leadership.epoch,
            "late_peer_steps": self.late_peer_steps,
            "flags_skipped": self.flags_out.skipped,
            "decode": stats,
        }

    def _loop(self, stop: Stoppable) -> None:
        last_frame = time.monotonic()
        while not stop.is_set():
            try:
                frame = self.frames.get(timeout=0.1)
            except queue.Empty:
                if time.monotonic() - last_frame > self.options.frame_timeout_s:
                    log.warning(
                        "%s: no frame from the world for %.0f s, stopping (a host daemon "
                        "restarts it to rejoin)",
                        self.robot_id,
                        self.options.frame_timeout_s,
                    )
                    self.world_lost = True
                    return
                continue
            last_frame = time.monotonic()
            if frame.final:
                return
            self.step(frame)

    def _peers_for(self, frame: SenseFrame) -> tuple[dict[str, RobotState], dict[str, RobotFlags]]:
        """The states (and, in real time, flags) the agent core gets for this frame."""
        delay_s = max(self.scenario.comm_delay_s, frame.dt_s)
        if not self.lockstep:
            states = {p: pick_state(self.peers.values(p), frame.t_s) for p in self.watched}
            flags = {p: pick_state(self.flags.values(p), frame.t_s) for p in self._alive()}
            return (
                {p: s for p, s in states.items() if s is not None},
                {p: f for p, f in flags.items() if f is not None},
            )
        not_after = frame.t_s - delay_s
        needed = [p for p in self._alive() if p != self.robot_id]
        if frame.t_s - delay_s >= -EPS_S:

            def ready() -> bool:
                return all(_has_state(self.peers.values(p), not_after) for p in needed)

            if not self.peers.wait(ready, self.options.peer_wait_s):
                self.late_peer_steps += 1
        chosen = {p: pick_state(self.peers.values(p), not_after) for p in self._alive()}
        return {p: s for p, s in chosen.items() if s is not None}, {}

    def _alive(self) -> list[str]:
        return [r for r in self.formation.robot_ids if r not in self.dead]

    def step(self, frame: SenseFrame) -> StepOutput:
        """Answer one frame: step the agent core, publish state, events and command."""
        if self.steps == 0 and frame.tick > 0:
            # The fleet started without this process (a restart): join, do not lead.
            self.agent = Agent(
                self.robot_id,
                scenario=self.scenario,
                robot=self.robot,
                formation=self.formation,
                joining=True,
            )
        if self._flag_ring is not None:
            self._flag_ring.drain(self._on_flags)
        for ring in self._state_rings:
            ring.drain(self._on_state)
        peers, flags = self._peers_for(frame)  # (the bounded wait for peers is not step time)
        started = time.perf_counter()
        self._last_peers = peers
        odometry = Odometry(
            Pose2D(frame.x_m, frame.y_m, frame.theta_rad),
            Twist2D(frame.v_mps, frame.omega_radps),
            frame.t_s,
        )
        status = RobotStatus(
            sonar_ranges_m=frame.sonar_ranges_m, bumpers=frame.bumpers, motors_enabled=True
        )
        observation = Observation(odometry, status)
        out = self.agent.step(observation, peers, frame.t_s, None if self.lockstep else flags)
        self._publish(frame, out)
        self.steps += 1
        self.step_times_s.append(time.perf_counter() - started)
        if not self.lockstep:
            self._follow_path()  # the leader may have changed: hear the new path
        return out

    def _publish(self, frame: SenseFrame, out: StepOutput) -> None:
        assert self._session is not None  # noqa: S101 - only called inside run()
        fleet, rid = self.options.fleet, self.robot_id
        if self.publish_commands:  # first: the world (lockstep) waits on it
            command = VelocityCommand(
                robot_id=rid,
                tick=frame.tick,
                stamp_s=frame.t_s,
                v_mps=out.command.v_mps,
                omega_radps=out.command.omega_radps,
            )
            self._session.publish(robot_key(fleet, rid, "cmd"), command, reliable_block=True)
        self._session.publish(robot_key(fleet, rid, "state"), out.state)
        flags = out.flags
        if self.flags_out.due(flags):
            self._session.publish(robot_key(fleet, rid, "flags"), flags)
        # Its own flags and state, as published, are part of what the next step decides on.
        self.flags.push(rid, flags)
        self.peers.push(rid, out.state)
        if out.leadership is not None:
            change = out.leadership
            announcement = LeaderAnnouncement(
                leader_id=change.leader_id,
                epoch=change.epoch,
                stamp_s=change.t_s,
                previous_id=change.previous_id,
                reason=change.reason,
            )
            self._session.publish(leader_key(fleet), announcement, reliable_block=True)
        for event in out.events:
            message = AgentEvent(
                robot_id=rid,
                t_s=event.t_s,
                source=event.source,
                target=event.target,
                reason=event.reason,
            )
            self._session.publish(robot_key(fleet, rid, "event"), message, reliable_block=True)
            if self.telemetry is not None:
                self.telemetry.log_transition(
                    rid,
                    t_s=event.t_s,
                    source=event.source,
                    target=event.target,
                    reason=event.reason,
                )
        if self.telemetry is not None:
            self._log_step(frame, out)

    def _log_step(self, frame: SenseFrame, out: StepOutput) -> None:
        assert self.telemetry is not None  # noqa: S101 - checked by the caller
        if self.steps == 0:  # the state log starts with the state the robot starts in
            self.telemetry.log_transition(
                self.robot_id, t_s=frame.t_s, source="-", target=out.state.fsm_state,
                reason="agent started",
            )  # fmt: skip
        leader = self._last_peers.get(out.state.leader_id) if out.state.leader_id else None
        errors = None
        if leader is not None:
            errors = live_errors(
                self.formation, self.robot_id, out.state.pose, leader, t_s=frame.t_s
            )
        self.telemetry.log_step(
            self.robot_id,
            t_s=frame.t_s,
            step=frame.tick,
            pose=out.state.pose,
            cmd=out.command,
            measured=Twist2D(frame.v_mps, frame.omega_radps),
            slot_target=errors.slot_target if errors else None,
            errors=(errors.linear_pct, errors.angular_pct, errors.orientation_deg)
            if errors
            else None,
            sonar_rays=sonar_rays(self.robot, out.state.pose, frame.sonar_ranges_m),
            fsm_state=out.state.fsm_state,
            leader_id=out.state.leader_id,
        )

    def _report(self) -> AgentReport:
        dropped = self._session.stats.dropped if self._session else 0
        times = sorted(self.step_times_s) or [0.0]
        if self.telemetry is not None:  # the count is final once the last rows went out
            self.telemetry.flush(REPORT_FLUSH_S)
        return AgentReport(
            robot_id=self.robot_id,
            steps=self.steps,
            saturations=self.agent.limiter.saturations,
            accel_limited=self.agent.limiter.accel_limited,
            dropped_messages=dropped,
            late_peer_steps=self.late_peer_steps,
            step_p50_us=1e6 * times[len(times) // 2],
            step_p99_us=1e6 * times[min(len(times) - 1, round(0.99 * (len(times) - 1)))],
            telemetry_dropped=self.telemetry.dropped if self.telemetry else 0,
        )


def _has_state(states: list[RobotState], not_after_s: float) -> bool:
    return any(abs(s.stamp_s - not_after_s) <= EPS_S or s.stamp_s > not_after_s for s in states)


__all__ = ["AgentRuntime", "RuntimeOptions", "pick_state", "robot_of"]
