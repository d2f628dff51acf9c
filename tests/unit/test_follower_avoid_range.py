"""How near an obstacle ahead has to be before a follower leaves its slot to go round it
(`navigation.avoid_range_m`, 0.2 m by default; the leader's is `deadlock.obstacle_range_m`).

A follower on its slot swings its heading from side to side as its slot's motion bends
(a slot 1 m behind a leader on its tightest arc moves 22 deg off the leader's heading),
so a corridor along its heading sweeps obstacles its slot passes clear of: set to about
the gap it stops in from cruise speed (0.2 m), it is blocked only by what it would have
to stop for. The leader's threshold, the one the group's deadlock rules read, is
unchanged; with reactive navigation off (the paper's scripted runs) every robot uses it.
"""

from __future__ import annotations

from phalanx.agents.agent import Agent, Observation
from phalanx.agents.sensing import release_gap_m
from phalanx.core.config import Scenario
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.peers import PeerState
from phalanx.core.robot import Odometry, RobotStatus

ROBOT = load_robot("p3dx")
# A line abreast of five led from its middle: nothing of the group ahead of anyone.
DEFAULT = load_scenario(CONFIG_ROOT / "scenarios" / "nav_corridor_collateral5.toml")
AVOID_M = DEFAULT.navigation.avoid_range_m
SCENARIO = DEFAULT
FORMATION = scenario_formation(SCENARIO)
LEADER = Pose2D(0.0, 0.0, 0.0)
FRONT = (3, 4)  # the P3DX ring's two sonars at +-10 deg, 0.166 m ahead of the axle


def _state(rid: str, pose: Pose2D, t_s: float = 0.0) -> PeerState:
    return PeerState(
        rid, 1, t_s, pose.x_m, pose.y_m, pose.theta_rad, 0.0, 0.0,
        "NAVIGATE" if rid == "r1" else "FORMATION_TRACK",
        leader_id=FORMATION.leader_of(rid) or "", formation_leader_id="r1", clear=True,
    )  # fmt: skip


def _gap_ahead_m(range_m: float) -> float:
    """The gap along the corridor ahead (the robot's radius plus `body_margin_m` to either
    side) to an echo `range_m` off its front sonars, whose beams cover straight ahead.
    """
    return 0.166 + range_m - (ROBOT.radius_m + SCENARIO.navigation.body_margin_m)


def _blocked(robot_id: str, range_m: float, scenario: Scenario = SCENARIO) -> bool:
    """Whether `robot_id`, on its slot, says it is blocked with both front sonars
    reading `range_m` (everything else far).
    """
    agent = Agent(robot_id, scenario=scenario, robot=ROBOT, formation=FORMATION)
    pose = FORMATION.slot_pose(robot_id, LEADER)
    ranges = tuple(range_m if i in FRONT else 5.0 for i in range(16))
    status = RobotStatus(sonar_ranges_m=ranges, bumpers=(False,), battery_v=12.6)
    peers = {
        rid: _state(rid, FORMATION.slot_pose(rid, LEADER))
        for rid in FORMATION.robot_ids
        if rid != robot_id
    }
    out = agent.step(Observation(Odometry(pose, Twist2D(0.0, 0.0), 0.0), status), peers, 0.0)
    return out.state.obstacle


def test_a_follower_is_blocked_only_nearer_than_the_leader() -> None:
    avoid_m, leader_m = AVOID_M, SCENARIO.deadlock.obstacle_range_m
    assert avoid_m < leader_m
    between = 0.45  # an echo in the gap between the two thresholds
    assert avoid_m < _gap_ahead_m(between) < leader_m
    navigation = SCENARIO.navigation.model_copy(update={"reshape": False})
    unfolding = SCENARIO.model_copy(update={"navigation": navigation})
    assert _blocked("r1", between, unfolding)
    # (a leader that can fold its group into a narrower shape folds it first)
    assert not _blocked("r1", between)
    assert not _blocked("r2", between)
    near = 0.2
    assert _gap_ahead_m(near) < avoid_m
    assert _blocked("r2", near)


def test_set_to_the_leader_s_range_a_follower_is_blocked_where_the_leader_is() -> None:
    leader_m = DEFAULT.deadlock.obstacle_range_m
    navigation = DEFAULT.navigation.model_copy(update={"avoid_range_m": leader_m})
    same = DEFAULT.model_copy(update={"navigation": navigation})
    assert _blocked("r2", 0.45, same)
    assert not _blocked("r2", 1.0, same)


def test_without_reactive_navigation_a_follower_keeps_the_leader_s_threshold() -> None:
    navigation = SCENARIO.navigation.model_copy(update={"reactive": False})
    scripted = SCENARIO.model_copy(update={"navigation": navigation})
    assert _blocked("r2", 0.45, scripted)
    assert not _blocked("r2", 1.0, scripted)


def test_a_follower_stopped_short_of_an_obstacle_goes_round_it() -> None:
    """Caught up at the speed limit, a follower brakes for an echo further off than
    `avoid_range_m`: standing there, it must not wait for a way that will not clear.
    """
    agent = Agent("r2", scenario=SCENARIO, robot=ROBOT, formation=FORMATION)
    pose = FORMATION.slot_pose("r2", LEADER)
    range_m = 0.38  # past avoid_range_m, short of the room the stop asks to start again
    release_m = release_gap_m(agent.parts.shape)
    assert AVOID_M < _gap_ahead_m(range_m) < release_m
    ranges = tuple(range_m if i in FRONT else 5.0 for i in range(16))
    status = RobotStatus(sonar_ranges_m=ranges, bumpers=(False,), battery_v=12.6)
    states = []
    for k in range(10):
        t_s = k * SCENARIO.dt_s
        peers = {
            rid: _state(rid, FORMATION.slot_pose(rid, LEADER), t_s)
            for rid in FORMATION.robot_ids
            if rid != "r2"
        }
        speed = 0.3 if k == 0 else 0.0  # moving at the first step, then stopped
        odometry = Odometry(pose, Twist2D(speed, 0.0), t_s)
        agent.step(Observation(odometry, status), peers, t_s)
        states.append(agent.fsm.state)
    assert states[0] == "EMERGENCY_STOP"
    assert "AVOID" in states  # (with `avoid_range_m` alone: stopped for good)
    assert states[-1] != "EMERGENCY_STOP"
