"""Keeping apart (hypothesis): two robots driven at each other never touch.

Each robot sees the other's pose one step late (the fleet's delay), slows down with the
spacing filter and brakes through the real limiter; the poses move by exact unicycle arcs.
"""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from phalanx.agents.control.limits import CommandLimiter
from phalanx.agents.control.spacing import (
    Spacing,
    closing_speed_cap_mps,
    keep_apart,
    near_sets,
)
from phalanx.agents.perception import braking_gap_m
from phalanx.core.config_files import load_robot
from phalanx.core.geometry import Pose2D, Twist2D, integrate_unicycle
from phalanx.core.limits import run_limits
from phalanx.core.peers import PeerState

DT_S = 0.1
ROBOT = load_robot("p3dx")
LIMITS = run_limits(ROBOT)
CONTACT_M = 2.0 * ROBOT.radius_m + 0.1


def _state(robot_id: str, pose: Pose2D) -> PeerState:
    return PeerState(robot_id, 0, 0.0, pose.x_m, pose.y_m, pose.theta_rad, 0.0, 0.0, "TRACK")


def _spacing(robot_id: str) -> Spacing:
    return Spacing(
        robot_id,
        contact_m=CONTACT_M,
        decel_mps2=LIMITS.emergency_decel_mps2,
        latency_s=2.0 * DT_S,
    )


@settings(max_examples=60, deadline=None)
@given(
    st.floats(0.9, 3.0),
    st.floats(-math.pi, math.pi),
    st.floats(-math.pi, math.pi),
    st.floats(-LIMITS.v_max_mps, LIMITS.v_max_mps),
    st.floats(-LIMITS.v_max_mps, LIMITS.v_max_mps),
    st.floats(-0.4, 0.4),
    st.floats(-0.4, 0.4),
)
def test_two_robots_driving_at_each_other_never_touch(
    d_m: float, th_a: float, th_b: float, v_a: float, v_b: float, w_a: float, w_b: float
) -> None:
    poses = {"a": Pose2D(0.0, 0.0, th_a), "b": Pose2D(d_m, 0.0, th_b)}
    wanted = {"a": Twist2D(v_a, w_a), "b": Twist2D(v_b, w_b)}
    spacing = {rid: _spacing(rid) for rid in poses}
    limiter = {rid: CommandLimiter(LIMITS) for rid in poses}
    heard = {rid: _state(rid, pose) for rid, pose in poses.items()}
    for _ in range(round(20.0 / DT_S)):
        commands = {}
        for rid, pose in poses.items():
            kept = spacing[rid].apply(wanted[rid], pose, heard)
            commands[rid] = limiter[rid].apply(kept, DT_S, brake_hard=spacing[rid].cut)
        heard = {rid: _state(rid, pose) for rid, pose in poses.items()}  # (a step late)
        poses = {rid: integrate_unicycle(poses[rid], commands[rid], DT_S) for rid in poses}
        gap = math.hypot(poses["a"].x_m - poses["b"].x_m, poses["a"].y_m - poses["b"].y_m)
        assert gap > 2.0 * ROBOT.radius_m


@given(st.floats(0.0, 2.0), st.floats(0.5, 3.0), st.floats(0.0, 0.3))
def test_the_cap_is_the_speed_that_brakes_within_half_the_gap(
    gap_m: float, decel: float, latency: float
) -> None:
    cap = closing_speed_cap_mps(gap_m, decel_mps2=decel, latency_s=latency)
    assert math.isclose(
        braking_gap_m(cap, decel_mps2=decel, latency_s=latency), gap_m / 2, abs_tol=1e-9
    )


def test_moving_away_or_turning_is_never_slowed() -> None:
    pose = Pose2D(0.0, 0.0, 0.0)
    near = {"b": _state("b", Pose2D(CONTACT_M + 0.01, 0.0, 0.0))}
    away = Twist2D(-0.3, 0.5)
    assert (
        keep_apart(away, pose, near, own_id="a", contact_m=CONTACT_M, decel_mps2=2.0, latency_s=0.2)
        is away
    )
    towards = keep_apart(
        Twist2D(0.3, 0.5),
        pose,
        near,
        own_id="a",
        contact_m=CONTACT_M,
        decel_mps2=2.0,
        latency_s=0.2,
    )
    assert 0.0 <= towards.v_mps < 0.05
    assert towards.omega_radps == 0.5


@given(
    st.lists(st.tuples(st.floats(-20.0, 20.0), st.floats(-20.0, 20.0)), min_size=1, max_size=40),
    st.floats(0.5, 5.0),
)
def test_near_sets_hold_exactly_the_robots_within_the_radius(
    points: list[tuple[float, float]], radius_m: float
) -> None:
    positions = {f"r{i}": p for i, p in enumerate(points)}
    near = near_sets(positions, radius_m=radius_m)
    for a, (xa, ya) in positions.items():
        for b, (xb, yb) in positions.items():
            d = math.hypot(xa - xb, ya - yb)
            if abs(d - radius_m) > 1e-9:
                assert (b in near[a]) == (d < radius_m), (a, b, d)
