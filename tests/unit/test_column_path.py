"""A column's followers keep to the path driven ahead of them (`navigation.column_path`):
the tail of a column whose leader turns is laid on the leader's path, not on a slot
swung out past it; the group's deadlock manoeuvres and its goal keep the rigid shape.
"""

from __future__ import annotations

import math

import pytest

from phalanx.agents.agent import Agent, Observation
from phalanx.core.config import Scenario
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.peers import PeerState
from phalanx.core.robot import Odometry, RobotStatus

ROBOT = load_robot("p3dx")
SCENARIO = load_scenario(CONFIG_ROOT / "scenarios" / "nav_corridor_inline3.toml")
FORMATION = scenario_formation(SCENARIO)
DT_S = SCENARIO.dt_s
SPEED_MPS = 0.3
STRAIGHT_M = 3.0  # the leader drives this far along x, then a left arc of RADIUS_M
RADIUS_M = 1.0
CLEAR = RobotStatus(sonar_ranges_m=(5.0,) * 16, bumpers=(False,), battery_v=12.6)


def _leader(t_s: float) -> tuple[Pose2D, float]:
    """The leader's pose at `t_s` and its turn rate."""
    s = SPEED_MPS * t_s
    if s <= STRAIGHT_M:
        return Pose2D(s, 0.0, 0.0), 0.0
    turned = (s - STRAIGHT_M) / RADIUS_M
    x = STRAIGHT_M + RADIUS_M * math.sin(turned)
    return Pose2D(x, RADIUS_M * (1.0 - math.cos(turned)), turned), SPEED_MPS / RADIUS_M


def _peer(rid: str, pose: Pose2D, omega: float, t_s: float, state: str) -> PeerState:
    return PeerState(
        rid, round(t_s / DT_S) + 1, t_s, pose.x_m, pose.y_m, pose.theta_rad, SPEED_MPS,
        omega, state, leader_id=FORMATION.leader_of(rid) or "", formation_leader_id="r1",
        clear=True,
    )  # fmt: skip


def _scenario(column_path: bool) -> Scenario:
    navigation = SCENARIO.navigation.model_copy(update={"column_path": column_path})
    return SCENARIO.model_copy(update={"navigation": navigation})


def _drive(
    column_path: bool, seconds: float, leader_state: str = "NAVIGATE"
) -> tuple[Agent, PeerState, list[Twist2D]]:
    """The third robot of the column, on its rigid slot, while its leader drives
    `_leader` for `seconds`: the agent, the leader's last state and every command.
    """
    agent = Agent("r3", scenario=_scenario(column_path), robot=ROBOT, formation=FORMATION)
    commands = []
    for k in range(round(seconds / DT_S)):
        t_s = k * DT_S
        pose, omega = _leader(t_s)
        lead = _peer("r1", pose, omega, t_s, leader_state)
        second = _peer("r2", FORMATION.slot_pose("r2", pose), omega, t_s, "FORMATION_TRACK")
        own = FORMATION.slot_pose("r3", pose)
        odometry = Odometry(own, Twist2D(SPEED_MPS, omega), t_s)
        out = agent.step(Observation(odometry, CLEAR), {"r1": lead, "r2": second}, t_s)
        commands.append(out.command)
    return agent, lead, commands


def _off_arc_m(pose: Pose2D) -> float:
    """How far `pose` lies off the leader's arc (its circle about (3, 1))."""
    return abs(math.hypot(pose.x_m - STRAIGHT_M, pose.y_m - RADIUS_M) - RADIUS_M)


def test_a_column_s_tail_keeps_to_the_leader_s_arc() -> None:
    # A half turn done (3.1 m of arc): the tail's slot, 2 m back along the path, on it.
    seconds = (STRAIGHT_M + RADIUS_M * math.pi) / SPEED_MPS
    agent, lead, _ = _drive(True, seconds)
    view = agent.view  # the last step's, at the leader's last stamp
    assert view is not None
    assert view.anchor == lead
    assert view.slot is not None
    on_path, (rigid, _) = agent.parts.track.target(view), view.slot
    assert on_path is not None
    assert _off_arc_m(on_path) < 0.01
    # heading along the arc at the point: the angle turned there
    turned = math.atan2(on_path.x_m - STRAIGHT_M, RADIUS_M - on_path.y_m)
    assert on_path.theta_rad == pytest.approx(turned, abs=0.02)
    # the rigid slot 2 m straight behind swings out past the arc: sqrt(1 + 4) - 1
    assert _off_arc_m(rigid) == pytest.approx(math.sqrt(5.0) - 1.0, abs=0.05)


def test_switched_off_the_tail_keeps_the_rigid_slot() -> None:
    seconds = (STRAIGHT_M + RADIUS_M * math.pi / 2) / SPEED_MPS
    agent, lead, _ = _drive(False, seconds)
    view = agent.view
    assert view is not None
    assert view.anchor == lead
    assert view.slot is not None
    assert agent.parts.track.target(view) == view.slot[0]


def test_on_a_straight_course_both_are_the_same_slot() -> None:
    *_, on_commands = _drive(True, 2.8 / SPEED_MPS)
    *_, off_commands = _drive(False, 2.8 / SPEED_MPS)
    assert on_commands[-1].v_mps == pytest.approx(off_commands[-1].v_mps, abs=1e-6)
    assert on_commands[-1].omega_radps == pytest.approx(off_commands[-1].omega_radps, abs=1e-6)


@pytest.mark.parametrize("leader_state", ["DEADLOCK_REVERSE", "DEADLOCK_TURN", "ARRIVED"])
def test_the_group_s_manoeuvres_use_the_rigid_shape(leader_state: str) -> None:
    """While the leader backs out of a deadlock, turns the shape or stands at its goal,
    the follower steers for its rigid slot (what the reverse starts from), on the bend
    as well; driving on, it keeps to the path.
    """
    seconds = (STRAIGHT_M + RADIUS_M * math.pi / 2) / SPEED_MPS
    _, _, on = _drive(True, seconds, leader_state)
    _, _, off = _drive(False, seconds, leader_state)
    assert on == off
    _, _, driving = _drive(True, seconds)
    assert abs(driving[-1].omega_radps - off[-1].omega_radps) > 0.05
