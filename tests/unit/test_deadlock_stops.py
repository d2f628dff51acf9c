"""A robot of the group stopping for an obstacle ends the leader's deadlock reverse; one
already stopped as the reverse began does not (it stopped for what lay ahead, which the
reverse moves the group away from) until it moves and stops again, unless it stopped
backing up (what stopped it lies where the reverse would take the group). The turn that
follows goes on whoever stops.

The leader is a whole `Agent`, fed the group's flags as they would arrive.
"""

from __future__ import annotations

import math
from typing import Any

from phalanx.agents.agent import Agent, Observation
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.peers import PeerState
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.core.states import State

ROBOT = load_robot("p3dx")
SCENARIO = load_scenario(CONFIG_ROOT / "scenarios" / "nav_deadend_wedge3.toml")
FORMATION = scenario_formation(SCENARIO)
FREE = RobotStatus(sonar_ranges_m=(5.0,) * 16, bumpers=(False,), battery_v=12.6)
# Facing across the way to the goal (19, 0): the turn is to be a quarter round.
HERE = Pose2D(0.0, 0.0, math.pi / 2)


def _flags(
    robot: str,
    k: int,
    t_s: float,
    state: str,
    *,
    stopped: bool = False,
    blocked: bool = True,
    way: int = 1,
) -> PeerState:
    slot = FORMATION.slot_pose(robot, HERE) if robot != "r1" else HERE
    return PeerState(
        robot, k, t_s, slot.x_m, slot.y_m, slot.theta_rad, 0.0, 0.0,
        State.EMERGENCY_STOP if stopped else state, obstacle=blocked, blocked_s=float(blocked),
        direction=way, formation_leader_id="r1", leader_id="" if robot == "r1" else "r1",
    )  # fmt: skip


class Group:
    """The leader r1 standing at `HERE`, stepped with the flags of r2 and r3 given."""

    def __init__(self, *, turning: bool = False) -> None:
        self.leader = Agent("r1", scenario=SCENARIO, robot=ROBOT, formation=FORMATION)
        self.k = 0
        self.turning = turning  # r1's heading follows its yaw rate (else it stays put)
        self.theta_rad = HERE.theta_rad

    def step(
        self,
        r2: str,
        r3: str,
        *,
        stopped: tuple[str, ...] = (),
        blocked: bool = True,
        backing: tuple[str, ...] = (),
    ) -> str:
        """One step (`blocked`: r1 reports an obstacle ahead; `backing`: the stopped robots
        that stopped while moving backwards); r1's state after it.
        """
        t_s = self.k * SCENARIO.dt_s
        flags = {"r1": _flags("r1", self.k, t_s, self.leader.state_name, blocked=blocked)}
        for robot, state in (("r2", r2), ("r3", r3)):
            way = -1 if robot in backing else 1
            flags[robot] = _flags(robot, self.k, t_s, state, stopped=robot in stopped, way=way)
        pose = Pose2D(HERE.x_m, HERE.y_m, self.theta_rad)
        observation = Observation(Odometry(pose, Twist2D(0.0, 0.0), t_s), FREE)
        command = self.leader.step(observation, flags, t_s).command
        if self.turning:
            self.theta_rad += command.omega_radps * SCENARIO.dt_s
        self.k += 1
        return self.leader.state_name

    def run(self, seconds: float, r2: str, r3: str, **how: Any) -> str:
        """Steps (`how` as for `step`) for `seconds`, or until r1's state changes; r1's
        state then.
        """
        before = self.leader.state_name
        for _ in range(round(seconds / SCENARIO.dt_s)):
            if self.step(r2, r3, **how) != before:
                break
        return self.leader.state_name

    def last_reason(self) -> str:
        """Why r1 took its last transition."""
        return self.leader.transitions[-1].reason


def _in_turn(group: Group) -> None:
    """Blocked all round: the reverse, ended by r2 stopping, then the turn."""
    track, rev = State.FORMATION_TRACK, State.FORMATION_REVERSE
    assert group.run(2.0, track, track) == State.DEADLOCK_REVERSE
    assert group.run(1.0, rev, rev) == State.DEADLOCK_REVERSE  # (nobody stopped: it goes on)
    assert group.run(1.0, rev, rev, stopped=("r2",)) == State.DEADLOCK_TURN
    assert "obstacle behind" in group.last_reason()


def test_the_turn_goes_on_while_robots_stop() -> None:
    group = Group()
    _in_turn(group)
    track = State.FORMATION_TRACK
    # r3 stopping as the shape swings round does not end the turn (ending it there left a
    # boxed-in group reversing and turning by inches, over and over): it goes on.
    assert group.run(3.0, track, track, stopped=("r2", "r3")) == State.DEADLOCK_TURN
    assert group.leader.limiter.last.omega_radps != 0.0


def test_a_robot_stopped_before_the_reverse_does_not_end_it() -> None:
    group = Group()
    track, rev = State.FORMATION_TRACK, State.FORMATION_REVERSE
    assert group.run(1.0, track, track, stopped=("r3",), blocked=False) == State.NAVIGATE
    assert group.run(2.0, track, track, stopped=("r3",)) == State.DEADLOCK_REVERSE
    assert group.run(2.0, rev, rev, stopped=("r3",)) == State.DEADLOCK_REVERSE
    assert group.run(1.0, rev, rev, stopped=("r2", "r3")) == State.DEADLOCK_TURN
    assert "obstacle behind" in group.last_reason()


def test_a_robot_passed_over_that_moves_and_stops_again_ends_the_reverse() -> None:
    group = Group()
    track, rev = State.FORMATION_TRACK, State.FORMATION_REVERSE
    assert group.run(1.0, track, track, stopped=("r3",), blocked=False) == State.NAVIGATE
    assert group.run(2.0, track, track, stopped=("r3",)) == State.DEADLOCK_REVERSE
    assert group.run(1.0, rev, rev, stopped=("r3",)) == State.DEADLOCK_REVERSE
    assert group.run(0.5, rev, rev) == State.DEADLOCK_REVERSE  # r3 moves with the group
    assert group.run(1.0, rev, rev, stopped=("r3",)) == State.DEADLOCK_TURN  # a new stop


def test_a_robot_stopped_backing_up_before_the_reverse_ends_it() -> None:
    group = Group()
    track = State.FORMATION_TRACK
    r3_back = {"stopped": ("r3",), "backing": ("r3",)}
    assert group.run(1.0, track, track, blocked=False, **r3_back) == State.NAVIGATE
    assert group.run(2.0, track, track, **r3_back) == State.DEADLOCK_REVERSE
    # The first step of the reverse already sees r3 in its way: straight to the turn.
    assert group.run(1.0, State.FORMATION_REVERSE, track, **r3_back) == State.DEADLOCK_TURN
    assert "obstacle behind" in group.last_reason()


def test_a_robot_still_stopped_behind_cuts_one_reverse_only() -> None:
    # Boxed in, a group would otherwise start and end reverses on the spot for ever: at
    # the next deadlock the robot still stopped is passed over, and the group backs away.
    group = Group(turning=True)
    track, rev = State.FORMATION_TRACK, State.FORMATION_REVERSE
    r3_back = {"stopped": ("r3",), "backing": ("r3",)}
    assert group.run(1.0, track, track, blocked=False, **r3_back) == State.NAVIGATE
    assert group.run(2.0, track, track, **r3_back) == State.DEADLOCK_REVERSE
    assert group.run(1.0, rev, track, **r3_back) == State.DEADLOCK_TURN
    assert group.run(30.0, track, track, **r3_back) == State.NAVIGATE
    assert group.run(2.0, track, track, **r3_back) == State.DEADLOCK_REVERSE
    assert group.run(1.0, rev, track, **r3_back) == State.DEADLOCK_REVERSE


def _stop_moving(v_mps: float) -> PeerState:
    """A follower that meets an obstacle all round while moving at `v_mps`: its state."""
    follower = Agent("r2", scenario=SCENARIO, robot=ROBOT, formation=FORMATION)
    near = RobotStatus(sonar_ranges_m=(0.3,) * 16, bumpers=(False,), battery_v=12.6)
    pose = FORMATION.slot_pose("r2", HERE)
    for k in range(3):
        t_s = k * SCENARIO.dt_s
        flags = {
            "r1": _flags("r1", k, t_s, State.NAVIGATE, blocked=False),
            "r2": _flags("r2", k, t_s, follower.state_name, blocked=False),
            "r3": _flags("r3", k, t_s, State.FORMATION_TRACK, blocked=False),
        }
        observation = Observation(Odometry(pose, Twist2D(v_mps, 0.0), t_s), near)
        state = follower.step(observation, flags, t_s).state
    assert follower.state_name == State.EMERGENCY_STOP
    return state


def test_a_stopped_robot_publishes_the_way_it_was_going() -> None:
    assert _stop_moving(-0.3).direction == -1
    assert _stop_moving(0.3).direction == 1
