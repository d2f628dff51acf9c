"""The agent process: Zenoh in, the agent core's step, the command out, telemetry.

With the `sim` driver the world drives the clock: each SenseFrame is a tick, answered
with a VelocityCommand for the same tick. In lockstep the agent first waits (bounded)
for the peer states the batch runner would give it (published `comm_delay_s` earlier),
which is what makes a multi-process run reproduce the in-process one.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass
from typing import Literal

from phalanx.agents.core import Agent, Observation, StepOutput
from phalanx.config import RobotParams, Scenario
from phalanx.drivers.base import Odometry, RobotStatus
from phalanx.formation import Formation, scenario_formation
from phalanx.geometry import Pose2D, Twist2D
from phalanx.messages import AgentEvent, AgentReport, RobotState, SenseFrame, VelocityCommand
from phalanx.metrics import live_errors
from phalanx.telemetry import Telemetry, sonar_rays
from phalanx.transport import (
    FleetSession,
    History,
    TransportConfig,
    alive_key,
    open_session,
    robot_key,
    robot_of,
    status_key,
)

log = logging.getLogger("phalanx.agent")
ClockMode = Literal["lockstep", "realtime"]
EPS_S = 1e-6


def pick_state(states: list[RobotState], not_after_s: float) -> RobotState | None:
    """The newest state stamped no later than `not_after_s`."""
    chosen = None
    for state in states:
        if state.stamp_s <= not_after_s + EPS_S and (
            chosen is None or state.stamp_s > chosen.stamp_s
        ):
            chosen = state
    return chosen


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
        self.frames: queue.Queue[SenseFrame] = queue.Queue()
        self.dead: set[str] = set()
        self.steps = 0
        self.late_peer_steps = 0
        self._session: FleetSession | None = None

    @property
    def watched(self) -> tuple[str, ...]:
        """Robots whose state this one needs: its leader, or everyone for the root."""
        leader = self.formation.leader_of(self.robot_id)
        if leader is None:
            return tuple(r for r in self.formation.robot_ids if r != self.robot_id)
        return (leader,)

    def run(self, stop: threading.Event) -> AgentReport:
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
        for peer in self.watched:
            session.subscribe(
                robot_key(fleet, peer, "state"),
                RobotState,
                lambda _k, s: self.peers.push(s.robot_id, s),
            )
        session.watch_alive(f"phalanx/{fleet}/alive/*", self._on_alive)
        session.serve_status(status_key(fleet, rid), self._status)

    def _on_alive(self, key: str, alive: bool) -> None:
        robot = key.rsplit("/", 1)[-1]
        if robot in self.watched:
            if alive:
                self.dead.discard(robot)
            else:
                self.dead.add(robot)
                self.peers.forget(robot)

    def _status(self) -> dict[str, object]:
        stats = self._session.stats.as_dict() if self._session else {}
        return {
            "robot_id": self.robot_id,
            "steps": self.steps,
            "state": self.agent.state_name,
            "late_peer_steps": self.late_peer_steps,
            "decode": stats,
        }

    def _loop(self, stop: threading.Event) -> None:
        last_frame = time.monotonic()
        while not stop.is_set():
            try:
                frame = self.frames.get(timeout=0.1)
            except queue.Empty:
                if time.monotonic() - last_frame > self.options.frame_timeout_s:
                    log.warning(
                        "%s: no frame for %.0f s, stopping",
                        self.robot_id,
                        self.options.frame_timeout_s,
                    )
                    return
                continue
            last_frame = time.monotonic()
            if frame.final:
                return
            self.step(frame)

    def _peers_for(self, frame: SenseFrame) -> dict[str, RobotState]:
        delay_s = max(self.scenario.comm_delay_s, frame.dt_s)
        not_after = frame.t_s - delay_s if self.options.clock == "lockstep" else frame.t_s
        needed = [p for p in self.watched if p not in self.dead]
        if self.options.clock == "lockstep" and frame.t_s - delay_s >= -EPS_S:

            def ready() -> bool:
                return all(_has_state(self.peers.values(p), not_after) for p in needed)

            if not self.peers.wait(ready, self.options.peer_wait_s):
                self.late_peer_steps += 1
        chosen = {p: pick_state(self.peers.values(p), not_after) for p in needed}
        return {p: s for p, s in chosen.items() if s is not None}

    def step(self, frame: SenseFrame) -> StepOutput:
        """Answer one frame: step the agent core, publish state, events and command."""
        peers = self._peers_for(frame)  # (the bounded wait for peers is not step time)
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
        out = self.agent.step(Observation(odometry, status), peers, frame.t_s)
        self._publish(frame, out)
        self.steps += 1
        self.step_times_s.append(time.perf_counter() - started)
        return out

    def _publish(self, frame: SenseFrame, out: StepOutput) -> None:
        assert self._session is not None  # noqa: S101 - only called inside run()
        fleet, rid = self.options.fleet, self.robot_id
        self._session.publish(robot_key(fleet, rid, "state"), out.state)
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
        command = VelocityCommand(
            robot_id=rid,
            tick=frame.tick,
            stamp_s=frame.t_s,
            v_mps=out.command.v_mps,
            omega_radps=out.command.omega_radps,
        )
        if self.publish_commands:
            self._session.publish(robot_key(fleet, rid, "cmd"), command, reliable_block=True)
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
            live = live_errors(self.formation, self.robot_id, out.state.pose, leader)
            errors = live
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
