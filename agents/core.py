"""The agent core: one robot's brain as a pure object, `step(observation, peers, t)`.

It does no I/O. The in-process batch runner calls it directly; the multi-process runtime
calls it between a Zenoh read and a driver write. Both feed it the same things, so a
scenario gives the same trajectory either way.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

from phalanx.agents.behaviours.formation import FollowerBehaviour
from phalanx.agents.behaviours.leader import LeaderBehaviour
from phalanx.agents.control import make_controller
from phalanx.agents.control.common import FollowerInput
from phalanx.agents.control.limits import CommandLimiter, KinematicLimits
from phalanx.agents.fsm import State, TransitionEvent
from phalanx.config import RobotParams, Scenario
from phalanx.drivers.base import Odometry, RobotStatus
from phalanx.formation import Formation
from phalanx.geometry import ZERO_TWIST, Twist2D
from phalanx.messages import RobotState

FRONT_HALF_ANGLE_RAD = math.radians(60.0)


@dataclass(frozen=True, slots=True)
class Observation:
    """What a robot senses this step (from its driver)."""

    odometry: Odometry
    status: RobotStatus


@dataclass(frozen=True, slots=True)
class StepOutput:
    """An agent step's result: the command to send, the state to publish, what changed."""

    command: Twist2D
    state: RobotState
    events: tuple[TransitionEvent, ...] = field(default_factory=tuple)


def front_sonar_indices(robot: RobotParams) -> tuple[int, ...]:
    """Sonars facing within 60 deg of straight ahead (they see what blocks the way)."""
    return tuple(
        i
        for i, unit in enumerate(robot.sonar.units)
        if abs(math.radians(unit.heading_deg)) <= FRONT_HALF_ANGLE_RAD
    )


def is_blocked(status: RobotStatus, front: tuple[int, ...], range_m: float) -> bool:
    """Whether something is within `range_m` ahead, or a bumper is pressed."""
    ranges = status.sonar_ranges_m
    near = any(ranges[i] < range_m for i in front if i < len(ranges))
    return near or any(status.bumpers)


class Agent:
    """One robot: the leader's behaviours or a follower's formation layer, plus limits."""

    def __init__(
        self, robot_id: str, *, scenario: Scenario, robot: RobotParams, formation: Formation
    ) -> None:
        self.robot_id = robot_id
        self.scenario = scenario
        self.formation = formation
        self.leader_id = formation.leader_of(robot_id)
        self.limiter = CommandLimiter(KinematicLimits.from_params(robot, scenario.limits))
        self.controller = make_controller(scenario.controller)
        self._front = front_sonar_indices(robot)
        self._seq = 0
        self._last_odometry: Odometry | None = None
        self.leader: LeaderBehaviour | None = None
        self.follower: FollowerBehaviour | None = None
        self.behaviour: LeaderBehaviour | FollowerBehaviour
        if self.leader_id is None:
            self.behaviour = self.leader = LeaderBehaviour(
                scenario.leader_profile, scenario.deadlock
            )
        else:
            self.behaviour = self.follower = FollowerBehaviour(
                scenario.controller.reverse_threshold_mps
            )

    @property
    def state_name(self) -> str:
        """The current behaviour state."""
        return self.behaviour.fsm.state

    @property
    def direction(self) -> int:
        """+1 forwards, -1 backwards."""
        return self.behaviour.direction

    @property
    def transitions(self) -> list[TransitionEvent]:
        """Every transition taken so far."""
        return self.behaviour.fsm.log

    def step(
        self, observation: Observation, peers: Mapping[str, RobotState], t_s: float
    ) -> StepOutput:
        """One control step at fleet time `t_s` with the latest states of other robots."""
        dt_s = self.scenario.dt_s
        blocked = is_blocked(
            observation.status, self._front, self.scenario.deadlock.obstacle_range_m
        )
        if self.leader is not None:
            event, wanted = self._lead(self.leader, observation, peers, blocked, t_s, dt_s)
        else:
            assert self.follower is not None  # noqa: S101 - set whenever leader is not
            event, wanted = self._follow(self.follower, observation, peers, t_s, dt_s)
        command = self.limiter.apply(wanted, dt_s)
        self._last_odometry = observation.odometry
        events = (event,) if event is not None else ()
        return StepOutput(command, self._state(observation.odometry, command, blocked, t_s), events)

    def _lead(
        self,
        leader: LeaderBehaviour,
        observation: Observation,
        peers: Mapping[str, RobotState],
        blocked: bool,
        t_s: float,
        dt_s: float,
    ) -> tuple[TransitionEvent | None, Twist2D]:
        others = [r for r in self.formation.robot_ids if r != self.robot_id]
        blocked_ids = tuple(r for r in others if r in peers and peers[r].obstacle)
        everyone = blocked and len(blocked_ids) == len(others)
        leader.observe(
            blocked=((self.robot_id,) if blocked else ()) + blocked_ids,
            everyone_blocked=everyone,
            odometry_step_m=self._travelled_m(observation.odometry),
        )
        event = leader.update(t_s)
        return event, leader.wanted_twist(dt_s)

    def _follow(
        self,
        follower: FollowerBehaviour,
        observation: Observation,
        peers: Mapping[str, RobotState],
        t_s: float,
        dt_s: float,
    ) -> tuple[TransitionEvent | None, Twist2D]:
        leader_id = self.formation.leader_of(self.robot_id) or ""
        lead = peers.get(leader_id)
        fresh = lead is not None and t_s - lead.stamp_s <= self.scenario.leader_timeout_s
        follower.observe(
            leader_v_mps=lead.v_mps if lead else 0.0,
            leader_direction=lead.direction if lead else 1,
            leader_fresh=fresh,
        )
        event = follower.update(t_s)
        if lead is None or follower.fsm.state == State.HOLD:
            return event, ZERO_TWIST
        inp = FollowerInput(
            follower=observation.odometry.pose,
            follower_twist=observation.odometry.twist,
            leader=lead.pose,
            leader_twist=lead.twist,
            leader_age_s=max(0.0, t_s - lead.stamp_s),
            slot=self.formation.slot_of(self.robot_id, leader_id),
            direction=follower.direction,
            dt_s=dt_s,
        )
        return event, self.controller.command(inp)

    def _travelled_m(self, odometry: Odometry) -> float:
        if self._last_odometry is None:
            return 0.0
        return (odometry.pose.position - self._last_odometry.pose.position).norm()

    def _state(self, odometry: Odometry, command: Twist2D, blocked: bool, t_s: float) -> RobotState:
        # The published twist is the command being executed from t_s on: a follower that
        # dead-reckons over the state's age then lands where the leader really is.
        self._seq += 1
        pose, twist = odometry.pose, command
        return RobotState(
            robot_id=self.robot_id,
            seq=self._seq,
            stamp_s=t_s,
            x_m=pose.x_m,
            y_m=pose.y_m,
            theta_rad=pose.theta_rad,
            v_mps=twist.v_mps,
            omega_radps=twist.omega_radps,
            fsm_state=self.state_name,
            obstacle=blocked,
            direction=1 if self.direction > 0 else -1,
            leader_id=self.leader_id or "",
        )
