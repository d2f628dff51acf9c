"""An agent on a robot driver steers from its pose at the control instant, not at the
last SIP or TPDO: odometry is carried forward from its stamp, a bounded amount."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.robot import Odometry
from phalanx.runtime.robot_io import MAX_ODOMETRY_AGE_S, pose_at

finite = st.floats(min_value=-10.0, max_value=10.0, allow_nan=False)


def test_a_sip_read_80_ms_after_it_came_is_carried_80_ms_forward() -> None:
    odometry = Odometry(Pose2D(1.0, 0.0, 0.0), Twist2D(-0.3, 0.0), stamp_s=50.0)
    pose = pose_at(odometry, at_s=50.08)
    assert pose.x_m == pytest.approx(1.0 - 0.3 * 0.08)
    assert pose.y_m == pytest.approx(0.0, abs=1e-12)


def test_a_reading_newer_than_the_instant_is_carried_back_to_it() -> None:
    """A step run late (a loaded machine) still stands for its tick: a SIP that came
    after the tick's instant describes the robot a little later than that."""
    odometry = Odometry(Pose2D(1.0, 0.0, 0.0), Twist2D(0.3, 0.0), stamp_s=50.0)
    pose = pose_at(odometry, at_s=49.9)
    assert pose.x_m == pytest.approx(1.0 - 0.3 * 0.1)


@given(
    x=finite, y=finite, th=st.floats(-math.pi, math.pi), v=st.floats(-0.75, 0.75),
    w=st.floats(-5.0, 5.0), age=st.floats(0.0, 1e4),
)  # fmt: skip
def test_a_reading_far_from_the_instant_moves_the_pose_at_most_its_bound(
    x: float, y: float, th: float, v: float, w: float, age: float
) -> None:
    odometry = Odometry(Pose2D(x, y, th), Twist2D(v, w), stamp_s=0.0)
    pose = pose_at(odometry, at_s=age)
    moved_m = math.hypot(pose.x_m - x, pose.y_m - y)
    # The arc formula subtracts sines at radius v / w: near the straight-line threshold
    # (|w| = 1e-9 rad/s) rounding leaves ~1e-7 of the bound (found by hypothesis: v 0.5,
    # w 1e-9, 0.12500005 m against 0.125 m); a relative 1e-5 covers it, nothing more.
    bound_m = abs(v) * min(abs(age), MAX_ODOMETRY_AGE_S)
    assert moved_m <= bound_m * (1.0 + 1e-5) + 1e-9
    turned = abs(math.remainder(pose.theta_rad - th, math.tau))
    assert turned <= abs(w) * min(abs(age), MAX_ODOMETRY_AGE_S) + 1e-9
