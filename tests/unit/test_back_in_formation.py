"""When a robot that left its slot counts as back in formation: within `formed_m` of its
slot, or `formed_share` of the slot's distance from the robot it is laid out from. A
column's tail, 4 m behind its leader, is back 0.3 m off its slot; the second robot, 1 m
behind, is not; with `formed_share = 0` (one fixed distance for every slot) neither is.
"""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from phalanx.agents.agent import Agent, Observation
from phalanx.core.config import LeadershipConfig, Scenario
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.peers import PeerState
from phalanx.core.robot import Odometry, RobotStatus

ROBOT = load_robot("p3dx")
# A column of five led from its head: r2 1 m behind r1, ..., r5 4 m behind.
SCENARIO = load_scenario(CONFIG_ROOT / "scenarios" / "nav_corridor_inline5.toml")
FORMATION = scenario_formation(SCENARIO)
FREE = RobotStatus(sonar_ranges_m=(5.0,) * 16, bumpers=(False,), battery_v=12.6)
LEADER = Pose2D(0.0, 0.0, math.radians(10.0))


def _state(rid: str, pose: Pose2D, t_s: float) -> PeerState:
    return PeerState(
        rid, 1, t_s, pose.x_m, pose.y_m, pose.theta_rad, 0.0, 0.0,
        "NAVIGATE" if rid == "r1" else "FORMATION_TRACK",
        leader_id=FORMATION.leader_of(rid) or "", formation_leader_id="r1", clear=True,
    )  # fmt: skip


def _back_after_one_step(robot_id: str, off_m: float, scenario: Scenario) -> bool:
    """`robot_id`, out of formation, `off_m` sideways of its slot with its heading:
    whether one step (the others on their slots, the leader still) brings it back.
    """
    agent = Agent(robot_id, scenario=scenario, robot=ROBOT, formation=FORMATION)
    agent.formed = False
    slot = FORMATION.slot_pose(robot_id, LEADER)
    side = slot.theta_rad + math.pi / 2
    x_m, y_m = slot.x_m + off_m * math.cos(side), slot.y_m + off_m * math.sin(side)
    pose = Pose2D(x_m, y_m, slot.theta_rad)
    peers = {
        rid: _state(rid, FORMATION.slot_pose(rid, LEADER), 0.0)
        for rid in FORMATION.robot_ids
        if rid != robot_id
    }
    agent.step(Observation(Odometry(pose, Twist2D(0.0, 0.0), 0.0), FREE), peers, 0.0)
    return agent.formed


def _with_share(share: float) -> Scenario:
    leadership = SCENARIO.leadership.model_copy(update={"formed_share": share})
    return SCENARIO.model_copy(update={"leadership": leadership})


def test_a_column_s_tail_is_back_nearer_its_slot_than_a_tenth_of_its_distance() -> None:
    assert FORMATION.slot_of("r5", "r1").norm() == 4.0
    assert _back_after_one_step("r5", 0.3, SCENARIO)
    assert not _back_after_one_step("r5", 0.45, SCENARIO)
    assert not _back_after_one_step("r2", 0.3, SCENARIO)
    assert _back_after_one_step("r2", 0.05, SCENARIO)


def test_with_no_share_every_slot_has_the_same_fixed_distance() -> None:
    fixed = _with_share(0.0)
    assert not _back_after_one_step("r5", 0.3, fixed)
    assert _back_after_one_step("r5", 0.05, fixed)


@given(formed_m=st.floats(0.01, 1.0), share=st.floats(0.0, 0.5))
def test_the_distance_is_never_under_formed_m_and_grows_down_the_column(
    formed_m: float, share: float
) -> None:
    leadership = LeadershipConfig(formed_m=formed_m, formed_share=share)
    within = [
        Agent(rid, scenario=SCENARIO, robot=ROBOT, formation=FORMATION).parts.shape.formed_within_m(
            "r1", leadership
        )
        for rid in ("r2", "r3", "r4", "r5")
    ]
    assert formed_m <= within[0] <= within[1] <= within[2] <= within[3]
    for k, value in enumerate(within, start=1):  # r2 1 m behind r1, ..., r5 4 m
        assert value == max(formed_m, share * k)
