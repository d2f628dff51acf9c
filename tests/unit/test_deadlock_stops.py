"""A robot of the group stopping for an obstacle ends the leader's deadlock reverse; one
already stopped as the reverse began does not (it stopped for what lay ahead, which the
reverse moves the group away from). The turn that follows goes on whoever stops.

The leader is a whole `Agent`, fed the group's flags as they would arrive.
"""

from __future__ import annotations

import math

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
    robot: str, k: int, t_s: float, state: str, *, stopped: bool = False, blocked: bool = True
) -> PeerState:
    slot = FORMATION.slot_pose(robot, HERE) if robot != "r1" else HERE
    return PeerState(
        robot, k, t_s, slot.x_m, slot.y_m, slot.theta_rad, 0.0, 0.0,
        State.EMERGENCY_STOP if stopped else state, obstacle=blocked, blocked_s=float(blocked),
        formation_leader_id="r1", leader_id="" if robot == "r1" else "r1",
    )  # fmt: skip


class Group:
    """The leader r1 standing at `HERE`, stepped with the flags of r2 and r3 given."""

    def __init__(self) -> None:
        self.leader = Agent("r1", scenario=SCENARIO, robot=ROBOT, formation=FORMATION)
        self.k = 0

    def step(self, r2: str, r3: str, *, stopped: tuple[str, ...] = (), blocked: bool = True) -> str:
        """One step (`blocked`: r1 reports an obstacle ahead); r1's state after it."""
        t_s = self.k * SCENARIO.dt_s
        flags = {
            "r1": _flags("r1", self.k, t_s, self.leader.state_name, blocked=blocked),
            "r2": _flags("r2", self.k, t_s, r2, stopped="r2" in stopped),
            "r3": _flags("r3", self.k, t_s, r3, stopped="r3" in stopped),
        }
        observation = Observation(Odometry(HERE, Twist2D(0.0, 0.0), t_s), FREE)
        self.leader.step(observation, flags, t_s)
        self.k += 1
        return self.leader.state_name

    def run(
        self,
        seconds: float,
        r2: str,
        r3: str,
        *,
        stopped: tuple[str, ...] = (),
        blocked: bool = True,
    ) -> str:
        """Steps for `seconds`, or until r1's state changes; r1's state then."""
        before = self.leader.state_name
        for _ in range(round(seconds / SCENARIO.dt_s)):
            if self.step(r2, r3, stopped=stopped, blocked=blocked) != before:
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
