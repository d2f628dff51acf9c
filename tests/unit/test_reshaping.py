"""The leader's choice of shape and the slide between shapes (agents/reshape.py)."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import cast

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from phalanx.agents.behaviours.base import Moment
from phalanx.agents.behaviours.leader import SQUEEZE_WINDOW, squeezed
from phalanx.agents.navigation import HEADINGS_RAD, Clearances, heading_index
from phalanx.agents.navigation.clearance import AHEAD_INDEX
from phalanx.agents.navigation.grid import OCCUPIED, OccupancyMap
from phalanx.agents.perception import NO_OBSTACLE_M
from phalanx.agents.reshape import (
    RESHAPE_CRUISE_MPS,
    RESHAPE_PEAK_MPS,
    SQUEEZE_FROM_M,
    SQUEEZE_S,
    Arrived,
    Reshape,
    ShapeKeeper,
)
from phalanx.agents.shape import Shape
from phalanx.core.config import NavigationConfig
from phalanx.core.config_files import load_robot
from phalanx.core.formation import resolve_formation
from phalanx.core.geometry import Pose2D, Twist2D, Vec2
from phalanx.core.limits import KinematicLimits
from phalanx.core.scenarios import formation_shape
from phalanx.core.shapes import COLUMN, SCENARIO_SHAPE, SHRUNK, ShapeBook, ShapeKey

ROBOT = load_robot("p3dx")
FORMATION = resolve_formation(formation_shape("collateral", 3))


def keeper(shape: str = "collateral", robots: int = 3) -> ShapeKeeper:
    return ShapeKeeper(ShapeBook(resolve_formation(formation_shape(shape, robots))), ROBOT.radius_m)


def moment(t_s: float) -> Moment:
    """A step's time: all a reshape without a drive reads."""
    return cast(Moment, SimpleNamespace(t_s=t_s))


def reshape_for(k: ShapeKeeper) -> Reshape:
    limits = KinematicLimits.from_params(ROBOT)
    shape = Shape("r1", FORMATION, radius_m=ROBOT.radius_m, nav=NavigationConfig(),
                  limits=limits, dt_s=0.1)  # fmt: skip
    return Reshape(k, shape, dt_s=0.1)


def test_a_fold_wanted_half_way_through_an_unfold_slides_back_from_where_the_slots_are() -> None:
    k = keeper()
    k.key, k.wanted = ShapeKey(COLUMN, COLUMN, 1.0), SCENARIO_SHAPE  # folded; unfold wanted
    behaviour = reshape_for(k)
    behaviour.enter(moment(0.0))
    for step in range(20):
        behaviour.command(moment(0.1 * step))
    halfway = k.key
    assert (halfway.source, halfway.target) == (COLUMN, SCENARIO_SHAPE)
    assert 0.0 < halfway.morph < 1.0
    before = k.book.positions(halfway)
    assert k.fold()  # the sonar: the way ahead is too narrow for the shape after all
    behaviour.command(moment(2.0))
    turned = k.key
    assert (turned.source, turned.target) == (SCENARIO_SHAPE, COLUMN)
    step_back = ShapeKey(turned.source, turned.target, turned.morph - 0.1 / behaviour.duration_s)
    after = k.book.positions(step_back)
    for rid, p in before.items():  # no jump: the slide goes on from where it was
        assert (after[rid] - p).norm() < 1e-9
    for step in range(400):
        behaviour.command(moment(2.1 + 0.1 * step))
    assert k.key == ShapeKey(SCENARIO_SHAPE, COLUMN, 1.0)


def test_a_leader_that_arrives_mid_unfold_stands_still_while_the_slide_ends() -> None:
    k = keeper()
    k.key, k.wanted = ShapeKey(COLUMN, COLUMN, 1.0), SCENARIO_SHAPE
    behaviour = reshape_for(k)
    behaviour.enter(moment(0.0))
    for step in range(10):
        behaviour.command(moment(0.1 * step))
    behaviour.leave(moment(1.0))  # the goal is reached: RESHAPE -> ARRIVED
    arrived = Arrived(behaviour)
    arrived.enter(moment(1.0))
    morphs = [k.key.morph]
    for step in range(400):
        twist = arrived.command(moment(1.1 + 0.1 * step))
        assert (twist.v_mps, twist.omega_radps) == (0.0, 0.0)
        morphs.append(k.key.morph)
    assert morphs[0] < 1.0
    assert morphs == sorted(morphs)  # on to the end, never back
    assert k.key == ShapeKey(COLUMN, SCENARIO_SHAPE, 1.0)  # in the scenario's shape
    arrived.leave(moment(41.0))
    assert k.wanted == SCENARIO_SHAPE


def test_the_shapes_are_not_weighed_again_and_a_squeeze_is_not_counted_mid_slide() -> None:
    k = keeper("collateral", 5)  # (a group that folds on the squeeze)
    grid = OccupancyMap(Vec2(0.0, 0.0))
    k.key, k.wanted = ShapeKey(SCENARIO_SHAPE, COLUMN, 0.5), COLUMN
    for step in range(50):
        k.decide(grid, Pose2D(0.0, 0.0, 0.0), Vec2(20.0, 0.0), 10.0 + step)
        k.squeeze(True, 0.1)
    assert k.wanted == COLUMN
    assert k.squeezed_s == 0.0
    k.key = ShapeKey(SCENARIO_SHAPE, SCENARIO_SHAPE, 1.0)
    k.wanted = SCENARIO_SHAPE
    for _ in range(round(SQUEEZE_S / 0.1) + 1):
        k.squeeze(True, 0.1)
    assert k.wanted == COLUMN  # settled, the same squeeze folds the group


@pytest.mark.parametrize(
    ("shape", "robots", "drive_m"),
    [("wedge", 3, 0.72), ("collateral", 3, 1.10), ("wedge", 5, 1.45), ("collateral", 5, 2.19)],
)
def test_only_a_group_whose_fold_is_long_folds_ahead_on_the_squeeze(
    shape: str, robots: int, drive_m: float
) -> None:
    k = keeper(shape, robots)
    assert k.slide_drive_m == pytest.approx(drive_m, abs=0.01)
    for _ in range(round(SQUEEZE_S / 0.1) + 1):
        k.squeeze(True, 0.1)
    assert k.squeezed_s >= SQUEEZE_S  # counted either way: no wider shape is taken meanwhile
    folds = k.wanted == k.book.distinct[-1]
    assert folds == (drive_m >= SQUEEZE_FROM_M)
    k.squeeze(False, 0.1)
    assert k.squeezed_s == 0.0


class Cruising:
    """The navigation behaviour a reshaping leader drives on with, wanting its cruise
    speed along a gentle bend.
    """

    has_goal = True
    drove_forward: Twist2D | None = None

    def command(self, moment: Moment) -> Twist2D:
        self.drove_forward = Twist2D(0.3, 0.1)
        return self.drove_forward


@pytest.mark.parametrize(("shape", "robots"), [("wedge", 3), ("collateral", 3), ("collateral", 5)])
def test_the_leader_drives_on_at_its_pace_while_the_shape_narrows_and_slowly_while_it_widens(
    shape: str, robots: int
) -> None:
    k = keeper(shape, robots)
    behaviour = reshape_for(k)
    behaviour.drive = Cruising()
    k.wanted = COLUMN
    behaviour.enter(moment(0.0))
    folding = [behaviour.command(moment(0.1 * step)) for step in range(400)]
    assert behaviour.reshaped
    assert k.key == ShapeKey(SCENARIO_SHAPE, COLUMN, 1.0)
    assert all(t == Twist2D(0.3, 0.1) for t in folding)  # its followers drop back
    behaviour.leave(moment(40.0))
    k.wanted = SCENARIO_SHAPE
    behaviour.enter(moment(50.0))
    unfolding = [behaviour.command(moment(50.0 + 0.1 * step)) for step in range(400)]
    assert behaviour.reshaped
    assert k.key == ShapeKey(COLUMN, SCENARIO_SHAPE, 1.0)
    for t in unfolding:  # they come up beside it: it waits for them, on the same curve
        assert t.v_mps == pytest.approx(RESHAPE_CRUISE_MPS)
        assert t.omega_radps / t.v_mps == pytest.approx(0.1 / 0.3)


@pytest.mark.parametrize(
    ("shape", "robots"), [("wedge", 3), ("wedge", 5), ("collateral", 3), ("collateral", 5)]
)
@pytest.mark.parametrize("v_max", [0.3, KinematicLimits.from_params(ROBOT).v_max_mps])
def test_a_narrowing_slide_lets_the_leader_on_as_fast_as_every_follower_can_keep_to_its_slot(
    shape: str, robots: int, v_max: float
) -> None:
    """`v_max`: the paper's bound (the navigation scenarios'), and the P3DX's rating."""
    k = keeper(shape, robots)
    for source, target in [(SCENARIO_SHAPE, SHRUNK), (SCENARIO_SHAPE, COLUMN), (SHRUNK, COLUMN)]:
        k.key = ShapeKey(source, target, 0.5)
        cap = k.drive_cap_mps(v_max)
        a, b = k.book.shapes[source], k.book.shapes[target]
        longest = max((b[r] - a[r]).norm() for r in a)
        fastest = max(
            math.hypot(cap + (b[r] - a[r]).x_m * RESHAPE_PEAK_MPS / longest,
                       (b[r] - a[r]).y_m * RESHAPE_PEAK_MPS / longest)
            for r in a
        )  # fmt: skip
        assert fastest <= v_max + 1e-9, (source, target)
        assert fastest == pytest.approx(v_max) or cap == v_max  # no slower than it may
        if target == COLUMN:
            assert cap == pytest.approx(v_max)  # into a column the followers drop back
    for source, target in [(COLUMN, SCENARIO_SHAPE), (SHRUNK, SCENARIO_SHAPE), (COLUMN, SHRUNK)]:
        k.key = ShapeKey(source, target, 0.5)
        assert k.drive_cap_mps(v_max) == RESHAPE_CRUISE_MPS  # they come up beside it


@pytest.mark.parametrize("ahead_m", [0.0, 1.0, 2.0])
def test_a_wider_shape_fits_only_with_room_for_it_here_and_on_ahead(ahead_m: float) -> None:
    k = keeper()
    k.key = ShapeKey(COLUMN, COLUMN, 1.0)
    grid = OccupancyMap(Vec2(0.0, 0.0))
    pose = Pose2D(0.0, 0.0, math.radians(30.0))
    assert k.fits(grid, pose, SCENARIO_SHAPE)
    # an obstacle where a slot of the line abreast will be, `ahead_m` on
    left = k.book.shapes[SCENARIO_SHAPE]["r2"]
    spot = pose.to_world(Vec2(left.x_m + ahead_m, left.y_m))
    row, col, _ = grid.index(np.array([spot.x_m]), np.array([spot.y_m]))
    grid.evidence[row, col] = OCCUPIED
    assert not k.fits(grid, pose, SCENARIO_SHAPE)
    assert k.fits(grid, pose, COLUMN)  # the column it is in passes there


def clearances(wide_m: dict[int, float], *, narrow_m: float = NO_OBSTACLE_M) -> Clearances:
    """Every heading free for the shape and the leader, but where `wide_m` says."""
    wide = np.full(HEADINGS_RAD.size, NO_OBSTACLE_M)
    for offset, free_m in wide_m.items():
        wide[(AHEAD_INDEX + offset) % HEADINGS_RAD.size] = free_m
    return Clearances(wide=wide, narrow=np.full(HEADINGS_RAD.size, narrow_m))


def test_the_sonar_squeezes_the_shape_only_where_no_heading_near_the_route_is_free_for_it() -> None:
    nav = NavigationConfig()
    blocked = dict.fromkeys(range(-SQUEEZE_WINDOW, SQUEEZE_WINDOW + 1), 1.0)
    # straight on blocked for the shape, a heading 7.5 deg off free: the steering takes it
    assert not squeezed(clearances({0: 1.0}), 0.0, 10.0, nav)
    assert not squeezed(clearances({**blocked, SQUEEZE_WINDOW: NO_OBSTACLE_M}), 0.0, 10.0, nav)
    assert squeezed(clearances(blocked), 0.0, 10.0, nav)
    # the leader alone blocked too: no squeeze (its own obstacle behaviour takes over)
    assert not squeezed(clearances(blocked, narrow_m=1.0), 0.0, 10.0, nav)
    # the goal nearer than the obstacle: nothing to squeeze through
    assert not squeezed(clearances(blocked), 0.0, 0.9, nav)


@given(
    wide=st.lists(st.floats(0.0, 6.0), min_size=HEADINGS_RAD.size, max_size=HEADINGS_RAD.size),
    desired_rad=st.floats(-math.pi, math.pi),
    dist_m=st.floats(0.1, 30.0),
)
def test_a_squeeze_leaves_no_heading_near_the_route_free_for_the_shape(
    wide: list[float], desired_rad: float, dist_m: float
) -> None:
    nav = NavigationConfig()
    clear = Clearances(wide=np.array(wide), narrow=np.full(HEADINGS_RAD.size, NO_OBSTACLE_M))
    need_m = min(nav.lookahead_m, dist_m)
    i = heading_index(desired_rad)
    near = [wide[(i + k) % len(wide)] for k in range(-SQUEEZE_WINDOW, SQUEEZE_WINDOW + 1)]
    assert squeezed(clear, desired_rad, dist_m, nav) == all(w < need_m for w in near)
