"""A leader bending its course slows further while a robot of the group is off its slot,
so that robot has speed left to catch up with its slot.
"""

from __future__ import annotations

import math

from phalanx.agents.agent import Agent, Observation
from phalanx.agents.behaviours.leader import CATCH_UP_SHARE
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.peers import PeerState
from phalanx.core.robot import Odometry, RobotStatus

ROBOT = load_robot("p3dx")
# A wedge of five, the goal 24 m straight on (+x); every sonar sees nothing.
SCENARIO = load_scenario(CONFIG_ROOT / "scenarios" / "nav_field_wedge5.toml")
FREE = RobotStatus(sonar_ranges_m=(5.0,) * 16, bumpers=(False,), battery_v=12.6)
# The leader faces 30 deg right of the goal: it bends left towards it.
HEADING_RAD = math.radians(-30.0)


def _leader_speed(lagging: str | None) -> float:
    """The leader's forward speed after 3 s of steering for the goal, with robot
    `lagging` (if any) off its slot in its flags and every other one on it.
    """
    formation = scenario_formation(SCENARIO)
    agent = Agent("r1", scenario=SCENARIO, robot=ROBOT, formation=formation)
    pose = Pose2D(0.0, 0.0, HEADING_RAD)
    twist = Twist2D(0.0, 0.0)
    for k in range(30):
        t_s = k * SCENARIO.dt_s
        peers = {}
        for rid in formation.robot_ids[1:]:
            slot = formation.slot_pose(rid, pose)
            peers[rid] = PeerState(
                rid, k, t_s, slot.x_m, slot.y_m, slot.theta_rad, twist.v_mps, twist.omega_radps,
                "FORMATION_TRACK", leader_id=formation.leader_of(rid) or "",
                formation_leader_id="r1", clear=True, formed=rid != lagging,
            )  # fmt: skip
        out = agent.step(Observation(Odometry(pose, twist, t_s), FREE), peers, t_s)
        twist = out.command
    assert out.state.fsm_state == "NAVIGATE"
    assert twist.omega_radps > 0.0  # (bending left, towards the goal)
    return twist.v_mps


def test_a_robot_off_its_slot_slows_the_leader_on_a_bend() -> None:
    formed = _leader_speed(None)
    lagging = _leader_speed("r5")
    assert 0.0 < formed < SCENARIO.navigation.cruise_mps  # (the bend alone slows it)
    assert lagging < formed
    # Every slot's speed scales with the leader's along the same arc.
    assert math.isclose(lagging / formed, CATCH_UP_SHARE, rel_tol=1e-6)
