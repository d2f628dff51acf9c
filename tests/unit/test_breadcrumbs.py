"""The leader's path (`phalanx.agents.navigation.Breadcrumbs`): whether a point lies on the
way it came, which tells a dead end's route (back along it) from one turning round the
end of a wall it drove along."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from phalanx.agents.navigation import Breadcrumbs
from phalanx.core.geometry import Vec2


def _driven(length_m: float) -> Breadcrumbs:
    # every point kept: in floats 0.05 k - 0.05 (k - 1) can come out a hair under 0.05,
    # which the default spacing would drop, leaving a 10 cm gap in the path
    crumbs = Breadcrumbs(20.0, spacing_m=0.049)
    for k in range(round(length_m / 0.05) + 1):
        crumbs.drop(Vec2(0.05 * k, 0.0))
    return crumbs


def test_a_point_beside_the_way_it_came_lies_on_it() -> None:
    crumbs = _driven(10.0)
    assert crumbs.came_by(Vec2(5.0, 0.9), within_m=1.0, skip_m=2.0) is True
    assert crumbs.came_by(Vec2(5.0, -1.2), within_m=1.0, skip_m=2.0) is False


def test_the_ground_the_robot_stands_on_is_left_out() -> None:
    crumbs = _driven(10.0)  # (it stands at x = 10)
    assert crumbs.came_by(Vec2(9.5, 0.5), within_m=1.0, skip_m=2.0) is False
    assert crumbs.came_by(Vec2(8.5, 0.5), within_m=1.0, skip_m=2.0) is True


def test_a_path_no_longer_than_what_is_left_out_says_nothing() -> None:
    assert _driven(1.5).came_by(Vec2(0.0, 0.0), within_m=1.0, skip_m=2.0) is None
    assert Breadcrumbs(20.0).came_by(Vec2(0.0, 0.0), within_m=1.0, skip_m=2.0) is None


@given(
    st.floats(min_value=0.0, max_value=7.5),
    st.floats(min_value=0.0, max_value=2 * math.pi),
    st.floats(min_value=0.0, max_value=3.0),
)
def test_came_by_is_the_distance_to_the_path_before_the_last_stretch(
    along_m: float, angle_rad: float, off_m: float
) -> None:
    # the path x = 0..10 on y = 0, the last 2 m left out: within 1 m of x = 0..8
    point = Vec2(along_m + off_m * math.cos(angle_rad), off_m * math.sin(angle_rad))
    nearest = Vec2(min(max(point.x_m, 0.0), 8.0), 0.0)
    distance_m = (point - nearest).norm()
    if abs(distance_m - 1.0) > 0.06:  # (the path is points 5 cm apart)
        assert _driven(10.0).came_by(point, within_m=1.0, skip_m=2.0) is (distance_m < 1.0)
