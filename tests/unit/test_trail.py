"""The tracked robot's path (`phalanx.agents.navigation.column_path.Trail`): the point and
heading a given distance back along it, and when it starts again."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from phalanx.agents.navigation.column_path import HEADING_CHORD_M, JUMP_M, KEPT_M, SPACING_M, Trail
from phalanx.core.geometry import Vec2


def _straight(trail: Trail, length_m: float, step_m: float = 0.01) -> Vec2:
    x = 0.0
    while x <= length_m + 1e-9:
        trail.hear("r1", Vec2(x, 0.0), 0.3)
        x += step_m
    return Vec2(x - step_m, 0.0)


def test_on_a_straight_path_the_slot_is_straight_behind() -> None:
    trail = Trail()
    end = _straight(trail, 3.0)
    pose = trail.pose_back(end, 1.0)
    assert pose is not None
    assert (pose.x_m, pose.y_m, pose.theta_rad) == pytest.approx((2.0, 0.0, 0.0), abs=1e-9)


def test_a_path_shorter_than_the_slot_is_far_gives_nothing() -> None:
    trail = Trail()
    end = _straight(trail, 0.8)
    assert trail.pose_back(end, 1.0) is None
    assert trail.pose_back(end, 0.5) is not None


def test_the_path_starts_again_on_a_reverse_a_jump_or_another_robot() -> None:
    for interruption in (
        ("r1", Vec2(3.0, 0.0), -0.1),  # the tracked robot backs up over its path
        ("r1", Vec2(3.0 + 2 * JUMP_M, 0.0), 0.3),  # not heard for a while
        ("r2", Vec2(3.0, 0.0), 0.3),  # another robot tracked
    ):
        trail = Trail()
        end = _straight(trail, 3.0)
        assert trail.pose_back(end, 1.0) is not None
        trail.hear(*interruption)
        assert len(trail) == 1
        assert trail.pose_back(interruption[1], 1.0) is None


@settings(max_examples=200, deadline=None)
@given(
    radius_m=st.floats(0.4, 5.0),
    side=st.sampled_from([-1.0, 1.0]),
    turn_rad=st.floats(0.3, 3.0),
    behind_m=st.floats(0.3, 2.0),
)
def test_the_slot_lies_on_the_driven_arc_its_distance_back_along_it(
    radius_m: float, side: float, turn_rad: float, behind_m: float
) -> None:
    """A robot drives 2.5 m straight, then an arc: the slot `behind_m` back lies on what it
    drove (within the sag of the recorded chords), `behind_m` of path from its end, and
    heads the way it was driven there.
    """
    ds = 0.005
    straight_m = 2.5
    s = np.arange(0.0, straight_m + radius_m * turn_rad, ds)
    on_arc = np.clip(s - straight_m, 0.0, None) / radius_m  # angle turned
    xs = np.where(s <= straight_m, s, straight_m + radius_m * np.sin(on_arc))
    ys = np.where(s <= straight_m, 0.0, side * radius_m * (1.0 - np.cos(on_arc)))
    trail = Trail()
    for x, y in zip(xs, ys, strict=True):
        trail.hear("r1", Vec2(float(x), float(y)), 0.3)
    end = Vec2(float(xs[-1]), float(ys[-1]))
    pose = trail.pose_back(end, behind_m)
    assert pose is not None
    gaps = np.hypot(xs - pose.x_m, ys - pose.y_m)
    k = int(np.argmin(gaps))
    sag_m = SPACING_M**2 / (8 * radius_m) + 1e-6
    assert gaps[k] <= sag_m + ds
    assert abs((s[-1] - s[k]) - behind_m) <= 0.01 + ds
    # The heading driven there, within the turn over the chord the heading is taken on.
    tangent_rad = side * float(on_arc[k])
    within_rad = HEADING_CHORD_M / (2 * radius_m) + 0.01
    assert abs(math.remainder(pose.theta_rad - tangent_rad, math.tau)) < within_rad


def test_a_long_path_keeps_its_last_stretch() -> None:
    trail = Trail()
    end = _straight(trail, 30.0, step_m=0.05)
    near = trail.pose_back(end, KEPT_M - 1.0)
    assert near is not None
    assert near.x_m == pytest.approx(end.x_m - (KEPT_M - 1.0), abs=1e-9)
    assert trail.pose_back(end, 29.0) is None  # long forgotten
    assert len(trail) <= 2 * (KEPT_M / SPACING_M + 2)
