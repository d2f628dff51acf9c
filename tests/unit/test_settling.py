"""A follower beside a leader standing still settles onto its slot: its position first
(a turn, a straight drive, to within `ON_SLOT_M`), then its heading (a turn on the
spot). Tracking a point alone
stops with that point on the slot and the axle and heading off, which the group's next
move (a reverse out of a dead end) would start with.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

from hypothesis import given, settings
from hypothesis import strategies as st

from phalanx.agents.agent import Agent, Observation, StepOutput
from phalanx.agents.behaviours.follower import ALIGN_AFTER_S, ON_SLOT_M, SETTLED_RAD
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import Pose2D, Twist2D, wrap_angle
from phalanx.core.peers import PeerState
from phalanx.core.robot import Odometry, RobotStatus

ROBOT = load_robot("p3dx")
# A wedge of three: r2's slot 1 m behind and to the side of its leader's.
SCENARIO = load_scenario(CONFIG_ROOT / "scenarios" / "nav_corridor_wedge3.toml")
FORMATION = scenario_formation(SCENARIO)
FREE = RobotStatus(sonar_ranges_m=(5.0,) * 16, bumpers=(False,), battery_v=12.6)
LEADER = Pose2D(0.0, 0.0, math.radians(20.0))
SLOT = FORMATION.slot_pose("r2", LEADER)


def _leader(seq: int, t_s: float) -> PeerState:
    return PeerState(
        "r1", seq, t_s, LEADER.x_m, LEADER.y_m, LEADER.theta_rad, 0.0, 0.0, "NAVIGATE",
        formation_leader_id="r1", clear=True,
    )  # fmt: skip


def _steps(start: Pose2D, seconds: float) -> Iterator[tuple[float, Pose2D, StepOutput, Pose2D]]:
    """r2 from `start` beside its still leader for `seconds`, its commands integrated
    exactly: at each step, the time, the pose it stepped from, what it put out and the
    pose its command took it to.
    """
    agent = Agent("r2", scenario=SCENARIO, robot=ROBOT, formation=FORMATION)
    dt_s = SCENARIO.dt_s
    pose, twist = start, Twist2D(0.0, 0.0)
    for k in range(round(seconds / dt_s)):
        t_s = k * dt_s
        observation = Observation(Odometry(pose, twist, t_s), FREE)
        out = agent.step(observation, {"r1": _leader(k, t_s)}, t_s)
        twist = out.command
        heading = pose.theta_rad + twist.omega_radps * dt_s / 2
        moved = Pose2D(
            pose.x_m + twist.v_mps * dt_s * math.cos(heading),
            pose.y_m + twist.v_mps * dt_s * math.sin(heading),
            wrap_angle(pose.theta_rad + twist.omega_radps * dt_s),
        )
        yield t_s, pose, out, moved
        pose = moved


def _settle(start: Pose2D, seconds: float) -> tuple[Pose2D, float, float]:
    """r2 from `start` for `seconds` (`_steps`): where it ends, and once it settles (its
    leader still for `ALIGN_AFTER_S`, before which the controller tracks the slot; plus
    the limiter's 1 s to slow down from what the controller asked) the fastest it drove
    and how much further from its slot it got than it was then.
    """
    pose = start
    fastest_mps, settling_from_m, furthest_m = 0.0, math.inf, 0.0
    for t_s, _, out, pose in _steps(start, seconds):
        if t_s >= ALIGN_AFTER_S + 1.0:
            fastest_mps = max(fastest_mps, abs(out.command.v_mps))
            settling_from_m = min(settling_from_m, _off_m(pose))
            furthest_m = max(furthest_m, _off_m(pose) - settling_from_m)
    return pose, fastest_mps, furthest_m


def _off_m(pose: Pose2D) -> float:
    return math.hypot(pose.x_m - SLOT.x_m, pose.y_m - SLOT.y_m)


def _aside(distance_m: float, bearing_deg: float, heading_deg: float) -> Pose2D:
    """`distance_m` from the slot, towards `bearing_deg` of the slot's heading."""
    b = SLOT.theta_rad + math.radians(bearing_deg)
    return Pose2D(
        SLOT.x_m + distance_m * math.cos(b),
        SLOT.y_m + distance_m * math.sin(b),
        SLOT.theta_rad + math.radians(heading_deg),
    )


def test_a_follower_swung_sideways_settles_onto_its_slot_position_and_heading() -> None:
    # As the turn back before a dead end's reverse leaves it: 0.2 m to the side of its
    # slot, turned 80 deg towards it.
    pose, fastest_mps, _ = _settle(_aside(0.2, -90.0, -80.0), 15.0)
    assert _off_m(pose) <= 0.005 + 1e-9  # (a reverse starts from here)
    assert abs(math.degrees(wrap_angle(pose.theta_rad - SLOT.theta_rad))) < 0.3
    assert 0.0 < fastest_mps <= 0.1 + 1e-9  # it drove, slowly


def test_on_its_slot_it_only_turns() -> None:
    start = _aside(0.8 * ON_SLOT_M, 90.0, 30.0)
    pose, fastest_mps, _ = _settle(start, 6.0)
    assert fastest_mps == 0.0
    assert abs(math.degrees(wrap_angle(pose.theta_rad - SLOT.theta_rad))) < 0.3


@settings(max_examples=30, deadline=None)
@given(
    distance_m=st.floats(0.02, 0.45),
    bearing_deg=st.floats(-180.0, 180.0),
    heading_deg=st.floats(-170.0, 170.0),
)
def test_from_anywhere_near_its_slot_it_ends_on_it_without_wandering_off(
    distance_m: float, bearing_deg: float, heading_deg: float
) -> None:
    pose, fastest_mps, further_m = _settle(_aside(distance_m, bearing_deg, heading_deg), 20.0)
    assert _off_m(pose) <= 0.005 + 1e-9  # (a reverse starts from here)
    assert abs(math.degrees(wrap_angle(pose.theta_rad - SLOT.theta_rad))) < 0.5
    assert fastest_mps <= 0.1 + 1e-9
    assert further_m <= 0.005  # drives onto it, not round it


def test_it_says_it_has_settled_once_on_its_slot_at_its_heading_and_not_before() -> None:
    # What a leader pausing before a deadlock reverse waits for (`pause_until_settled`).
    said = [
        (out.state.settled, _off_m(pose), abs(wrap_angle(pose.theta_rad - SLOT.theta_rad)))
        for _, pose, out, _ in _steps(_aside(0.2, -90.0, -80.0), 15.0)
    ]
    first = next(i for i, (settled, _, _) in enumerate(said) if settled)
    assert first * SCENARIO.dt_s > ALIGN_AFTER_S  # not while it was still on its way
    assert all(settled for settled, _, _ in said[first:])  # nothing moved it off again
    for settled, off_m, heading_off_rad in said:
        if settled:
            assert off_m <= ON_SLOT_M + 1e-9
            assert heading_off_rad <= SETTLED_RAD + 1e-9
