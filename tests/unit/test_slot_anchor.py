"""A follower of a follower lays its slot out from the formation's leader, not from the
robot between: that robot's own corrections (a swing of its heading, a lag) do not
reach the robots behind it, so errors do not add up down a chain.
"""

from __future__ import annotations

import math

from phalanx.agents.agent import Agent, Observation, StepOutput
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.peers import PeerState
from phalanx.core.robot import Odometry, RobotStatus

ROBOT = load_robot("p3dx")
# A chain of three, 1 m apart: r2 follows r1, r3 follows r2.
SCENARIO = load_scenario(CONFIG_ROOT / "scenarios" / "nav_corridor_inline3.toml")
FREE = RobotStatus(sonar_ranges_m=(5.0,) * 16, bumpers=(False,), battery_v=12.6)
STEPS = 40


def _state(rid: str, seq: int, t_s: float, pose: Pose2D, twist: Twist2D, leader: str) -> PeerState:
    return PeerState(
        rid, seq, t_s, pose.x_m, pose.y_m, pose.theta_rad, twist.v_mps, twist.omega_radps,
        "FORMATION_TRACK" if leader else "NAVIGATE", leader_id=leader,
        formation_leader_id="r1", clear=True,
    )  # fmt: skip


def _r3_commands(r2_heading_swing_rad: float, r2_aside_m: float) -> list[StepOutput]:
    """r3's steps behind a leader on a steady arc, with r2 off its own slot by
    `r2_aside_m` to its left and its heading swinging by up to `r2_heading_swing_rad`.
    """
    formation = scenario_formation(SCENARIO)
    agent = Agent("r3", scenario=SCENARIO, robot=ROBOT, formation=formation)
    lead_twist = Twist2D(0.2, 0.05)
    own = Pose2D(-2.0, 0.0, 0.0)
    outs = []
    for k in range(STEPS):
        t_s = k * SCENARIO.dt_s
        head = Pose2D(0.2 * t_s, 0.0, 0.05 * t_s)
        middle = formation.slot_pose("r2", head)
        swing = r2_heading_swing_rad * math.sin(2.0 * t_s)
        c, s = math.cos(head.theta_rad), math.sin(head.theta_rad)
        r2 = Pose2D(
            middle.x_m - s * r2_aside_m, middle.y_m + c * r2_aside_m, middle.theta_rad + swing
        )
        peers = {
            "r1": _state("r1", k, t_s, head, lead_twist, ""),
            "r2": _state("r2", k, t_s, r2, Twist2D(0.2, 0.7 * math.cos(2.0 * t_s)), "r1"),
        }
        odometry = Odometry(own, Twist2D(0.2, 0.05), t_s)
        outs.append(agent.step(Observation(odometry, FREE), peers, t_s))
    return outs


def test_the_robot_between_does_not_move_the_slot_of_the_robot_behind() -> None:
    steady = _r3_commands(0.0, 0.0)
    swinging = _r3_commands(math.radians(30.0), 0.3)
    assert all(o.state.leader_id == "r2" for o in steady)  # (it still tracks r2)
    assert [o.command for o in swinging] == [o.command for o in steady]
    assert any(o.command.v_mps > 0.0 for o in steady)


def test_without_the_leaders_state_the_slot_is_laid_out_from_the_robot_tracked() -> None:
    formation = scenario_formation(SCENARIO)
    commands = []
    for aside_m in (0.0, 0.3):
        agent = Agent("r3", scenario=SCENARIO, robot=ROBOT, formation=formation)
        r2 = Pose2D(-1.0, aside_m, 0.0)
        out = None
        for k in range(5):
            t_s = k * SCENARIO.dt_s
            head = _state("r1", k, t_s, Pose2D(0.0, 0.0, 0.0), Twist2D(0.2, 0.0), "")
            peers = {"r2": _state("r2", k, t_s, r2, Twist2D(0.2, 0.0), "r1")}
            odometry = Odometry(Pose2D(-2.0, 0.0, 0.0), Twist2D(0.2, 0.0), t_s)
            # (r1's flags heard, its state not: only the robot tracked sent one)
            out = agent.step(Observation(odometry, FREE), peers, t_s, {**peers, "r1": head})
        assert out is not None
        commands.append(out.command)
    assert commands[1].omega_radps > commands[0].omega_radps  # (it turns towards r2's side)
