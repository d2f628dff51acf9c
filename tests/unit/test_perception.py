"""Sonar geometry, corridor clearance, heading choice and the obstacle map."""

from __future__ import annotations

import math

import numpy as np
import pytest

from phalanx.agents.masking import _clearances
from phalanx.agents.navigation import (
    HEADINGS_RAD,
    OccupancyMap,
    clearance_along,
    corridor_clearance,
)
from phalanx.agents.navigation.steering import choose_heading
from phalanx.agents.perception import SonarGeometry, braking_gap_m
from phalanx.core.config_files import load_robot
from phalanx.core.geometry import Pose2D, Vec2

ROBOT = load_robot("p3dx")
SONAR = SonarGeometry.from_params(ROBOT)
MAX = ROBOT.sonar.max_range_m


def pts(*xy: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    return np.array([p[0] for p in xy]), np.array([p[1] for p in xy])


def test_clearance_of_a_point_dead_ahead_beside_and_inside() -> None:
    assert clearance_along(pts((2.0, 0.0)), 0.0, half_width_m=0.3) == pytest.approx(1.7)
    assert clearance_along(pts((2.0, 0.5)), 0.0, half_width_m=0.3) == math.inf
    assert clearance_along(pts((0.1, 0.0)), 0.0, half_width_m=0.3) == 0.0
    assert clearance_along(pts((-2.0, 0.0)), 0.0, half_width_m=0.3) == math.inf
    assert clearance_along(pts((-2.0, 0.0)), math.pi, half_width_m=0.3) == pytest.approx(1.7)


def test_formation_corridor_counts_every_slot() -> None:
    # An obstacle 2 m ahead of a follower 0.7 m to the left: not in the leader's way,
    # in the shape's.
    point = pts((1.3, 0.7))
    own = corridor_clearance(point, np.array([0.0]), half_width_m=0.3)
    shape = corridor_clearance(
        point, np.array([0.0]), half_width_m=0.3, origins=(Vec2(0, 0), Vec2(-0.7, 0.7))
    )
    assert own[0] == math.inf
    assert shape[0] == pytest.approx(1.7)


def test_max_range_reads_as_nothing_and_known_robots_are_not_obstacles() -> None:
    free = (MAX,) * 16
    assert SONAR.points(free)[0].size == 0
    near = list(free)
    near[3] = 0.5  # the 10 deg sonar sees something 0.5 m out
    x, _y = SONAR.points(near)
    assert x.size == 5
    assert np.all(x > 0.5)
    robot_there = Vec2(0.166 + 0.5 + 0.25, 0.1)
    assert SONAR.points(near, [(robot_there, 0.35)])[0].size == 0


def test_far_arcs_are_narrowed_near_ones_cover_the_blind_gap() -> None:
    far, near = [MAX] * 16, [MAX] * 16
    far[1], near[1] = 4.0, 0.8  # the 50 deg sonar, beside the 25 deg blind gap to 90 deg
    angles_far = np.degrees(np.arctan2(*reversed(SONAR.points(far))))
    angles_near = np.degrees(np.arctan2(*reversed(SONAR.points(near))))
    assert np.ptp(angles_far) < 10.0
    assert angles_near.max() > 62.0


def test_heading_choice_goes_round_and_keeps_its_side() -> None:
    wall = pts(*[(1.5, y) for y in np.linspace(-0.4, 0.4, 9)])
    narrow = corridor_clearance(wall, HEADINGS_RAD, half_width_m=0.3)
    index = choose_heading(0.0, wide=narrow, narrow=narrow, need_m=2.0)
    assert 0.2 < abs(HEADINGS_RAD[index]) <= math.pi / 2
    right = choose_heading(0.0, wide=narrow, narrow=narrow, need_m=2.0, previous_rad=-0.6)
    assert HEADINGS_RAD[right] < 0.0


def test_heading_choice_with_no_way_round_heads_for_the_goal() -> None:
    blocked = np.zeros_like(HEADINGS_RAD)
    index = choose_heading(0.3, wide=blocked, narrow=blocked, need_m=2.0, window_rad=1.0)
    assert HEADINGS_RAD[index] == pytest.approx(0.3, abs=math.radians(4))


def test_braking_gap() -> None:
    assert braking_gap_m(0.3, decel_mps2=0.3, latency_s=0.2) == pytest.approx(0.06 + 0.15)
    assert braking_gap_m(0.0, decel_mps2=0.3, latency_s=0.2) == 0.0


def _wall_reading(pose: Pose2D, wall_x: float) -> tuple[float, ...]:
    """What the ring reads facing a long wall at x = wall_x (centre rays, exact)."""
    ranges = []
    for unit in ROBOT.sonar.units:
        origin = pose.to_world(Vec2(unit.x_m, unit.y_m))
        heading = pose.theta_rad + math.radians(unit.heading_deg)
        c = math.cos(heading)
        r = (wall_x - origin.x_m) / c if c > 1e-6 else MAX
        ranges.append(min(MAX, r) if r > 0 else MAX)
    return tuple(ranges)


def test_map_remembers_a_wall_and_routes_round_it() -> None:
    grid = OccupancyMap(Vec2(0.0, 0.0))
    for y in np.arange(-2.0, 2.01, 0.5):  # drive along in front of a wall 1.5 m ahead
        pose = Pose2D(0.0, float(y), 0.0)
        for _ in range(3):
            grid.update(pose, SONAR, _wall_reading(pose, 1.5))
    assert grid.occupied().sum() > 5
    goal = Vec2(4.0, 0.0)
    carrot = grid.route(Vec2(0.0, 0.0), goal, keep_off_m=0.5, ahead_m=1.0)
    assert carrot is not None
    assert abs(carrot.y_m) > 1.5 or carrot.x_m < 1.0  # round the end of the wall, not through


def test_a_robot_of_the_formation_in_front_of_a_wall_does_not_clear_it() -> None:
    grid = OccupancyMap(Vec2(0.0, 0.0))
    pose = Pose2D(0.0, 0.0, 0.0)
    for _ in range(3):
        grid.update(pose, SONAR, _wall_reading(pose, 1.5))
    wall = grid.occupied().copy()
    assert wall.any()
    # A robot of the formation 0.8 m ahead: the beams that meet it read 0.8 m, and it is
    # masked out (no echo). What lies past it was not seen, however often it is read.
    ranges = np.array(_wall_reading(pose, 0.8))
    for _ in range(20):
        grid.update(pose, SONAR, ranges, np.zeros(ranges.shape, dtype=bool))
    assert (grid.occupied() & wall).sum() == wall.sum()
    # A beam that meets nothing sees its way clear: the same wall wears away.
    for _ in range(20):
        grid.update(pose, SONAR, np.full(ranges.shape, MAX))
    assert not (grid.occupied() & wall).any()


def test_an_echo_counts_most_on_its_beams_axis() -> None:
    # It came from somewhere on the beam's arc at its range, most likely near the axis.
    grid = OccupancyMap(Vec2(0.0, 0.0))
    unit = 3  # the front transducer looking 10 deg to the left
    ranges = np.full(SONAR.unit_x_m.size, MAX)
    ranges[unit] = 2.0
    grid.update(Pose2D(0.0, 0.0, 0.0), SONAR, ranges)
    heading = float(SONAR.unit_heading_rad[unit])
    half = SONAR.half_beam_rad

    def evidence_at(angle: float) -> int:
        x = SONAR.unit_x_m[unit] + 2.0 * math.cos(angle)
        y = SONAR.unit_y_m[unit] + 2.0 * math.sin(angle)
        row, col, _ = grid.index(np.array([x]), np.array([y]))
        return int(grid.evidence[row[0], col[0]])

    axis, left_edge = evidence_at(heading), evidence_at(heading + half)
    assert axis > left_edge > 0
    assert grid.occupied().sum() == 1  # one echo: only its axis's cell counts as occupied


def test_unknown_space_is_free_and_an_enclosed_goal_has_no_route() -> None:
    grid = OccupancyMap(Vec2(0.0, 0.0))
    assert grid.route(Vec2(0, 0), Vec2(5, 0), keep_off_m=0.5, ahead_m=1.0) == Vec2(5, 0)
    ring = np.linspace(0, 2 * math.pi, 80)
    grid._add(5 + 1.0 * np.cos(ring), 1.0 * np.sin(ring), 6)
    assert grid.route(Vec2(0, 0), Vec2(5, 0), keep_off_m=0.0, ahead_m=1.0) is None


def test_a_reading_short_of_the_ring_has_no_echo_and_raises_nothing() -> None:
    short = np.full(8, 0.5)  # a robot reporting 8 sonars where its parameter file has 16
    echo = SONAR.echoes(short, [(Vec2(1.0, 0.0), 0.35)])
    assert echo.shape == (16,)
    assert not echo.any()
    assert SONAR.points_of(short, echo)[0].size == 0
    assert SONAR.points(short)[0].size == 0
    grid = OccupancyMap(Vec2(0.0, 0.0))
    grid.update(Pose2D(0.0, 0.0, 0.0), SONAR, short, echo)


def test_an_echo_the_body_overlaps_blocks_only_the_ways_towards_it() -> None:
    """An echo at the body's edge (where one read at the sonar's minimum range is put)
    lies inside the corridor's disc: it blocks every heading it lies ahead of, and none
    of those leading away from it, so a robot standing against it can leave.
    """
    edge = pts((-0.251, 0.0))  # touching the body's back, half-width 0.3
    gaps = corridor_clearance(edge, HEADINGS_RAD, half_width_m=0.3)
    towards = np.cos(HEADINGS_RAD) < 0.0
    assert np.all(gaps[towards] == 0.0)
    assert np.all(gaps[~towards] == math.inf)
    assert clearance_along(edge, 0.0, half_width_m=0.3) == math.inf
    assert clearance_along(edge, math.pi, half_width_m=0.3) == 0.0
    x, y = edge
    batched = _clearances(x[None, :], y[None, :], np.ones((1, 1), dtype=bool), np.array([0.3]))
    assert batched[0, 0] == math.inf  # ahead
    assert batched[0, 1] < 0.0  # behind: overlapped (floored at 0 by its callers)
