"""Whether the scenario's shape fits the way, as the leader's map shows it, measured per
step and reported beside the time in the shape: the leader's shape keeper says so each
time it weighs the shapes, and gauges it while the slots slide or it does anything but
navigate (the scenario shape's footprint has a route about as good as the best, and the
way is as wide as the shape where the group is and along the leader's route), the run
records it per step (`RobotTrace.fits`), and the navigation metrics give
the share of steps it fits and the share of those the group was in the shape.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from phalanx.agents.navigation.grid import OCCUPIED, OccupancyMap
from phalanx.agents.reshape import (
    DECIDE_S,
    DETOUR_M,
    DETOUR_SHARE,
    FITS_ALONG_M,
    ShapeKeeper,
    _poses_along,
)
from phalanx.analysis.metrics import navigation_metrics
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.formation import resolve_formation
from phalanx.core.geometry import Pose2D, Vec2
from phalanx.core.runlog import RunLog
from phalanx.core.scenarios import formation_shape
from phalanx.core.shapes import COLUMN, SCENARIO_SHAPE, SHAPE_NAMES, ShapeBook, ShapeKey
from phalanx.core.states import State
from phalanx.runtime.batch import BatchRunner

ROBOT = load_robot("p3dx")
LINE = resolve_formation(formation_shape("collateral", 3))  # 2 m across, 0.26 m bodies
WALL_X_M = 4.0


def _walled(gap_half_m: float) -> OccupancyMap:
    """A map with a wall across the way at x = 4 m, open only within `gap_half_m` of y = 0."""
    grid = OccupancyMap(Vec2(0.0, 0.0))
    ys = np.arange(-15.0, 15.0, grid.cell_m / 2)
    ys = ys[np.abs(ys) > gap_half_m]
    row, col, _ = grid.index(np.full(ys.shape, WALL_X_M), ys)
    grid.evidence[row, col] = OCCUPIED
    return grid


@pytest.mark.parametrize(
    ("gap_half_m", "fits"),
    [(3.0, True), (0.8, False)],  # the line's footprint needs 1.41 m each side, the column's 0.41
)
def test_the_keeper_says_whether_the_scenario_shape_fits_the_way(
    gap_half_m: float, fits: bool
) -> None:
    keeper = ShapeKeeper(ShapeBook(LINE), ROBOT.radius_m)
    grid = _walled(gap_half_m)
    assert keeper.scenario_fits  # nothing weighed yet: assumed
    keeper.decide(grid, Pose2D(0.0, 0.0, 0.0), Vec2(8.0, 0.0), t_s=DECIDE_S)
    assert keeper.scenario_fits is fits
    # in the column the way fits or not just the same: it is the scenario's shape's way
    keeper.key = ShapeKey(COLUMN, COLUMN, 1.0)
    keeper.decide(grid, Pose2D(0.0, 0.0, 0.0), Vec2(8.0, 0.0), t_s=3 * DECIDE_S)
    assert keeper.scenario_fits is fits


def test_the_keeper_gauges_the_way_mid_slide_and_off_navigation_deciding_nothing() -> None:
    """Mid-slide `decide`, and `gauge` (the leader doing anything but navigating), say
    whether the shape fits, every `DECIDE_S`, and want no other shape.
    """
    keeper = ShapeKeeper(ShapeBook(LINE), ROBOT.radius_m)
    here, goal = Pose2D(0.0, 0.0, 0.0), Vec2(8.0, 0.0)
    keeper.key, keeper.wanted = ShapeKey(SCENARIO_SHAPE, COLUMN, 0.5), COLUMN
    keeper.decide(_walled(0.8), here, goal, t_s=DECIDE_S)
    assert not keeper.scenario_fits
    keeper.decide(_walled(3.0), here, goal, t_s=1.5 * DECIDE_S)
    assert not keeper.scenario_fits  # (not weighed again within DECIDE_S)
    keeper.decide(_walled(3.0), here, goal, t_s=2 * DECIDE_S)
    assert keeper.scenario_fits
    keeper.key = ShapeKey(COLUMN, COLUMN, 1.0)
    for step in range(3, 8):
        keeper.gauge(_walled(3.0 if step % 2 else 0.8), here, goal, t_s=step * DECIDE_S)
        assert keeper.scenario_fits is bool(step % 2)
    assert keeper.wanted == COLUMN  # a wider shape fits, yet none is wanted
    keeper.enabled = False
    keeper.gauge(_walled(0.8), here, goal, t_s=9 * DECIDE_S)
    assert keeper.scenario_fits  # (a keeper that never reshapes measures nothing)


def _blocked_at(*points: tuple[float, float]) -> OccupancyMap:
    """An empty map but for the cells holding `points`."""
    grid = OccupancyMap(Vec2(0.0, 0.0))
    xs, ys = np.array(points).T
    row, col, _ = grid.index(xs, ys)
    grid.evidence[row, col] = OCCUPIED
    return grid


def _straight(heading_rad: float, length_m: float = 6.0) -> tuple[Vec2, ...]:
    """A route's points every half metre from the origin along `heading_rad`."""
    return tuple(
        Vec2(d * math.cos(heading_rad), d * math.sin(heading_rad))
        for d in np.arange(0.5, length_m + 0.25, 0.5)
    )


def _gap(along_m: float, heading_rad: float) -> OccupancyMap:
    """Two short walls 2.5 m apart across the way `along_m` from the origin along
    `heading_rad`: 2 m free between their cells, less than the line abreast needs (its
    slots 1 m to either side, each a body and a margin, 0.41 m, clear).
    """
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    return _blocked_at(
        *(
            (a * c - side * s, a * s + side * c)
            for a in (along_m - 0.25, along_m + 0.25)
            for side in (-1.25, 1.25)
        )
    )


def test_the_shape_fits_the_way_only_where_the_way_along_the_route_is_wide_enough() -> None:
    """The line abreast: a gap too narrow for it 2 m on blocks it along a straight route,
    not along a route turning left before it; one 2 m up the turned route blocks that one
    alone. With no route, only where the group is counts; one wall alone it steers off.
    """
    keeper = ShapeKeeper(ShapeBook(LINE), ROBOT.radius_m)
    here = Pose2D(0.0, 0.0, 0.0)
    ahead = _gap(2.0, 0.0)
    assert not keeper.fits_along(ahead, here, _straight(0.0))
    assert keeper.fits_along(ahead, here, _straight(math.pi / 2))
    assert keeper.fits_along(ahead, here, ())
    up = _gap(2.0, math.pi / 2)
    assert keeper.fits_along(up, here, _straight(0.0))
    assert not keeper.fits_along(up, here, _straight(math.pi / 2))
    one_wall = _blocked_at((1.75, 1.25), (2.25, 1.25))
    assert keeper.fits_along(one_wall, here, _straight(0.0))  # (the row shifted right)
    # the weighing says so too: a way as good as any, but not room along it
    keeper.decide(ahead, here, Vec2(12.0, 0.0), t_s=DECIDE_S, route=_straight(0.0))
    assert not keeper.scenario_fits
    keeper.decide(ahead, here, Vec2(12.0, 0.0), t_s=3 * DECIDE_S, route=_straight(0.0)[:1])
    assert keeper.scenario_fits  # (a route ending before 1 m: where it is alone)


def _clear_within(grid: OccupancyMap, point: Vec2, radius_m: float) -> bool:
    """The plain check: no occupied cell's centre nearer than `radius_m` plus half a cell."""
    rows, cols = np.nonzero(grid.occupied())
    x = grid.x0_m + (cols + 0.5) * grid.cell_m
    y = grid.y0_m + (rows + 0.5) * grid.cell_m
    return bool((np.hypot(x - point.x_m, y - point.y_m) - grid.cell_m / 2 >= radius_m).all())


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.0, 1.5))
def test_the_map_says_at_once_what_it_says_point_by_point(seed: int, radius_m: float) -> None:
    rng = np.random.default_rng(seed)
    grid = OccupancyMap(Vec2(0.0, 0.0))
    grid.evidence[rng.random(grid.evidence.shape) < 0.02] = OCCUPIED
    points = [Vec2(*xy) for xy in rng.uniform(-42.0, 42.0, (int(rng.integers(0, 30)), 2))]
    plain = [_clear_within(grid, p, radius_m) for p in points]
    assert grid.clear_of(points, radius_m).tolist() == plain
    assert [grid.clear_within(p, radius_m) for p in points] == plain


def _best_weighing_every_shape(
    keeper: ShapeKeeper, grid: OccupancyMap, start: Vec2, goal: Vec2
) -> int | None:
    """The widest shape whose route is as good as the best, every shape's route planned."""
    shapes = [s for s in range(len(SHAPE_NAMES)) if s == 0 or keeper.book.differs(s)]
    lengths = {
        s: grid.route_length_m(start, goal, footprint_m=keeper.footprint_m(s)) for s in shapes
    }
    known = [m for m in lengths.values() if m is not None]
    if not known:
        return None
    longest = min(known) * DETOUR_SHARE + DETOUR_M
    return next(s for s in shapes if (math.inf if lengths[s] is None else lengths[s]) <= longest)


@settings(max_examples=100, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.floats(0.0, 0.3),
    st.sampled_from(["wedge", "collateral", "inline"]),
    st.tuples(st.floats(-10.0, 10.0), st.floats(-10.0, 10.0)),
)
def test_the_shapes_weighed_as_they_would_be_with_every_route_planned(
    seed: int, density: float, shape: str, goal_xy: tuple[float, float]
) -> None:
    """The weighing stops at the scenario's shape when its route is as good as any could
    be (no route is shorter than the fewest moves): the same shape as planning them all.
    """
    rng = np.random.default_rng(seed)
    grid = OccupancyMap(Vec2(0.0, 0.0), half_size_m=12.0)
    grid.evidence[rng.random(grid.evidence.shape) < density] = OCCUPIED
    keeper = ShapeKeeper(ShapeBook(resolve_formation(formation_shape(shape, 5))), ROBOT.radius_m)
    start, goal = Vec2(0.0, 0.0), Vec2(*goal_xy)
    assert keeper._best(grid, start, goal) == _best_weighing_every_shape(keeper, grid, start, goal)


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.tuples(st.floats(-5.0, 5.0), st.floats(-5.0, 5.0)), min_size=0, max_size=12),
    st.floats(-math.pi, math.pi),
)
def test_the_poses_along_a_route_are_its_first_points_that_far_on(
    xy: list[tuple[float, float]], theta_rad: float
) -> None:
    pose = Pose2D(0.5, -0.5, theta_rad)
    route = tuple(Vec2(x, y) for x, y in xy)
    poses = list(_poses_along(pose, route, FITS_ALONG_M))
    assert poses[0] == pose
    points = (pose.position, *route)
    steps = [(b - a).norm() for a, b in itertools.pairwise(points)]
    along = np.concatenate(([0.0], np.cumsum(steps)))
    reached = [d for d in FITS_ALONG_M if along[-1] >= d]
    assert len(poses) == 1 + len(reached)
    for at, d in zip(poses[1:], reached, strict=True):
        k = int(np.argmax(along >= d))  # the first point that far on
        assert (at.x_m, at.y_m) == (points[k].x_m, points[k].y_m)
        assert math.isfinite(at.theta_rad)


def _narrow_run() -> RunLog:
    scenario = load_scenario(CONFIG_ROOT / "scenarios" / "nav_corridor_wedge3.toml")
    return BatchRunner(scenario.model_copy(update={"duration_s": 50.0})).run()


def test_a_run_records_per_step_whether_the_shape_fits_and_its_metrics_count_it() -> None:
    log = _narrow_run()
    n = len(log.t_s)
    assert all(len(tr.fits) == n for tr in log.traces.values())
    lead = log.traces["r1"]
    assert lead.fits[0]  # an empty map: the shape fits
    assert not all(lead.fits)  # the corridor: not all the way
    followers = [log.traces[r].fits for r in ("r2", "r3")]
    assert all(all(f) for f in followers)  # (only the leader weighs the shapes)
    # measured on while the slots slide too, not held from before the slide
    assert any(
        lead.fits[k] != lead.fits[k - 1] and lead.states[k] == State.RESHAPE for k in range(1, n)
    )
    # known series in place of the run's: the metrics' arithmetic, step by step
    half = n // 2
    lead.fits = [k < half for k in range(n)]
    # in the shape from the start, or back in it from the column; every fourth step
    # on the way to the column
    lead.shapes = [
        (0, COLUMN, 0.5) if k % 4 == 0
        else (SCENARIO_SHAPE, SCENARIO_SHAPE, 1.0) if k < n // 3
        else (COLUMN, SCENARIO_SHAPE, 1.0)
        for k in range(n)
    ]  # fmt: skip
    metrics = navigation_metrics(log)
    assert metrics["fits_share"] == pytest.approx(half / n)
    kept = sum(1 for k in range(half) if k % 4)
    assert metrics["scenario_shape_when_fits"] == pytest.approx(kept / half)
    assert metrics["scenario_shape_share"] == pytest.approx(sum(1 for k in range(n) if k % 4) / n)


def test_a_folded_group_unfolds_where_the_map_shows_room_as_far_as_the_unfold_drives() -> None:
    """The line abreast of three, folded into the column: its leader drives on 1.10 m
    while the slots slide back, so the way must be seen as wide as the line 1, 2 and 3 m
    along the route. There it unfolds, also with an obstacle where a slot would be
    straight on (the row shifts off it); not where the way was never sensed, nor where a
    gap narrows it within those 3 m, nor on a route that ends before them.
    """
    keeper = ShapeKeeper(ShapeBook(LINE), ROBOT.radius_m)
    assert keeper.unfold_along_m == (1.0, 2.0, 3.0)
    here, route = Pose2D(0.0, 0.0, 0.0), _straight(0.0)
    unseen = _blocked_at((2.0, 1.0))
    seen = _blocked_at((2.0, 1.0))
    seen.seen[:] = True
    assert not keeper.fits(seen, here, SCENARIO_SHAPE)  # a slot's place 2 m on is taken
    assert keeper.unfolds_along(seen, here, route)
    assert not keeper.unfolds_along(unseen, here, route)
    assert not keeper.unfolds_along(seen, here, route[:4])  # (2 m of route)
    for along_m, room in ((3.0, False), (5.0, True)):
        narrowed = _gap(along_m, 0.0)
        narrowed.seen[:] = True
        assert keeper.unfolds_along(narrowed, here, route) is room

    def unfolded(grid: OccupancyMap) -> bool:
        keeper.key = ShapeKey(COLUMN, COLUMN, 1.0)
        keeper.wanted = COLUMN
        for k in (1, 2):
            keeper.decide(grid, here, Vec2(12.0, 0.0), t_s=(2 + 2 * k) * DECIDE_S, route=route)
        return keeper.wanted == SCENARIO_SHAPE

    assert unfolded(seen)
    assert not unfolded(unseen)
