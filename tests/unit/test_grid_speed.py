"""The occupancy grid's fast paths give what the plain algorithms they replace gave, bit
for bit: the route's wavefront (a bucketed Dijkstra, against relaxing every cell until
nothing changes), the furthest route point in sight (checked in batches, against one
segment at a time), a whole `plan`, the obstacles grown by a disc (row by row, against
every offset in turn), and the map update (against `np.unique` and clipping per call;
numpy's update and the compiled loop numba runs, each). The plain algorithms are kept
here, as they were, as the reference.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from phalanx.agents.navigation import FleetMap, fleet_map, grid
from phalanx.agents.navigation.grid import OccupancyMap
from phalanx.agents.perception import ARC_SPREAD_M, SonarGeometry
from phalanx.core.compiled import chosen
from phalanx.core.config_files import load_robot
from phalanx.core.geometry import Pose2D, Vec2
from phalanx.core.peers import Scan

SONAR = SonarGeometry.from_params(load_robot("p3dx"))
# The map updates' tests run on both paths (the dev extra installs numba).
both_paths = pytest.mark.parametrize("kind", ["numpy", "numba"])
Bools = npt.NDArray[np.bool_]
Floats = npt.NDArray[np.float64]


# --- the reference: the plain algorithms -------------------------------------------------


def ref_wavefront(blocked: Bools, cost: Floats, row: int, col: int) -> Floats:
    """Relax every cell from its eight neighbours until nothing changes (at most
    8 (h + w) sweeps)."""
    dist = np.full(blocked.shape, grid.UNREACHABLE)
    dist[row, col] = 0.0
    h, w = blocked.shape
    for _ in range(8 * (h + w)):
        best = dist
        for dy, dx, step in grid._MOVES:
            shifted = np.full_like(dist, grid.UNREACHABLE)
            shifted[max(dy, 0) : h + min(dy, 0), max(dx, 0) : w + min(dx, 0)] = dist[
                max(-dy, 0) : h + min(-dy, 0), max(-dx, 0) : w + min(-dx, 0)
            ]
            best = np.minimum(best, shifted + step * cost)
        best[blocked] = grid.UNREACHABLE
        best[row, col] = 0.0
        if np.array_equal(best, dist):
            break
        dist = best
    return dist


def ref_in_sight(
    m: OccupancyMap, a: Vec2, b: Vec2, blocked: Bools, offset: tuple[int, int]
) -> bool:
    steps = max(2, math.ceil((b - a).norm() / (m.cell_m / 2)))
    f = np.linspace(0.0, 1.0, steps)
    row, col, _ = m.index(a.x_m + f * (b.x_m - a.x_m), a.y_m + f * (b.y_m - a.y_m))
    row, col = row - offset[0], col - offset[1]
    h, w = blocked.shape
    inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
    return bool(inside.all()) and not bool(blocked[row, col].any())


def ref_grow(occupied: Bools, cells: int) -> Bools:
    """Every offset of the disc in turn, the obstacles moved by it."""
    grown = occupied.copy()
    h, w = occupied.shape
    for dy in range(-cells, cells + 1):
        for dx in range(-cells, cells + 1):
            if (dy or dx) and dy * dy + dx * dx <= cells * cells:
                shifted = np.zeros_like(occupied)
                shifted[max(dy, 0) : h + min(dy, 0), max(dx, 0) : w + min(dx, 0)] = occupied[
                    max(-dy, 0) : h + min(-dy, 0), max(-dx, 0) : w + min(-dx, 0)
                ]
                grown |= shifted
    return grown


def ref_plan(
    m: OccupancyMap,
    start: Vec2,
    goal: Vec2,
    *,
    keep_off_m: float,
    ahead_m: float,
    footprint_m: float,
) -> tuple[Vec2, float, tuple[Vec2, ...]] | None:
    window = m._window(start, goal)
    occupied = m.occupied()[window]
    blocked = ref_grow(occupied, grid._cells_within(footprint_m, m.cell_m))
    near = ref_grow(occupied, math.ceil(keep_off_m / m.cell_m - 0.5))
    cost = np.where(near, grid.NEAR_COST, 1.0)
    (r0, c0), (rg, cg) = m._cell(start, window), m._cell(goal, window)
    if not grid._on(blocked, rg, cg) or not grid._on(blocked, r0, c0):
        return None
    if footprint_m > 0.0 and blocked[rg, cg]:
        return None
    blocked[rg, cg] = False
    reach = grid._cells_within(footprint_m, m.cell_m)
    if reach:
        rows, cols = np.ogrid[: blocked.shape[0], : blocked.shape[1]]
        round_start = (rows - r0) ** 2 + (cols - c0) ** 2 <= reach * reach
        blocked &= ~round_start | occupied
    blocked[r0, c0] = False
    dist = ref_wavefront(blocked, cost, rg, cg)
    if dist[r0, c0] >= grid.UNREACHABLE:
        return None
    length_m = float(dist[r0, c0]) * m.cell_m
    offset = (window[0].start, window[1].start)
    path = [(r0, c0)]
    while path[-1] != (rg, cg) and len(path) < grid.MAX_PATH_CELLS:
        path.append(grid._downhill(dist, *path[-1]))
    points = [m.centre(r + offset[0], c + offset[1]) for r, c in path[1:]] + [goal]
    minimum = min(len(points) - 1, max(0, round(ahead_m / m.cell_m) - 1))
    for point in reversed(points[minimum:]):
        if ref_in_sight(m, start, point, blocked, offset):
            return point, length_m, tuple(points)
    return points[minimum], length_m, tuple(points)


def ref_add(m: OccupancyMap, x: Floats, y: Floats, amount: int) -> None:
    row, col, inside = m.index(x, y)
    keep = inside.astype(bool)
    row, col = row[keep], col[keep]
    if row.size == 0:
        return
    cells = np.unique(row * m.cells + col)
    flat = m.evidence.reshape(-1)
    flat[cells] = np.clip(flat[cells].astype(np.int16) + amount, 0, grid.MAX_EVIDENCE)
    m.seen.reshape(-1)[cells] = True


def ref_update(m: OccupancyMap, pose: Pose2D, ranges: Floats, echo: Bools) -> None:
    units = SONAR.unit_x_m.size
    if ranges.size < units:
        return
    r = ranges[:units]
    c, s = math.cos(pose.theta_rad), math.sin(pose.theta_rad)
    ox = pose.x_m + c * SONAR.unit_x_m - s * SONAR.unit_y_m
    oy = pose.y_m + s * SONAR.unit_x_m + c * SONAR.unit_y_m
    heading = pose.theta_rad + SONAR.unit_heading_rad
    reach = np.where(SONAR.ranged(r), r - m.cell_m, grid.FREE_REACH_M)
    steps = np.arange(0.0, float(reach.max(initial=0.0)), m.cell_m / 2)
    if steps.size:
        along = steps[None, :]
        mask = along < reach[:, None]
        x = (ox[:, None] + along * np.cos(heading)[:, None])[mask]
        y = (oy[:, None] + along * np.sin(heading)[:, None])[mask]
        ref_add(m, x, y, -1)
    near = echo & (r < grid.MAP_RANGE_M)
    half = np.minimum(SONAR.half_beam_rad, np.arctan2(ARC_SPREAD_M, np.maximum(r, 1e-6)))
    for offset, amount in ((-1.0, grid.EDGE_HIT), (0.0, grid.HIT), (1.0, grid.EDGE_HIT)):
        angle = heading + offset * half
        hx, hy = ox + r * np.cos(angle), oy + r * np.sin(angle)
        ref_add(m, hx[near], hy[near], amount)


# --- random grids ------------------------------------------------------------------------


@st.composite
def grids(draw: st.DrawFn) -> tuple[Bools, Floats, tuple[int, int], tuple[int, int]]:
    """A window: closed cells, each cell's cost (1 or `NEAR_COST`), a goal and a start."""
    h, w = draw(st.integers(1, 24)), draw(st.integers(1, 24))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    blocked = rng.random((h, w)) < draw(st.floats(0.0, 0.6))
    cost = np.where(rng.random((h, w)) < draw(st.floats(0.0, 1.0)), grid.NEAR_COST, 1.0)
    goal = (draw(st.integers(0, h - 1)), draw(st.integers(0, w - 1)))
    start = (draw(st.integers(0, h - 1)), draw(st.integers(0, w - 1)))
    blocked[goal] = blocked[start] = False
    return blocked, cost, goal, start


def _path(dist: Floats, start: tuple[int, int], goal: tuple[int, int]) -> list[tuple[int, int]]:
    path = [start]
    while path[-1] != goal and len(path) < grid.MAX_PATH_CELLS:
        path.append(grid._downhill(dist, *path[-1]))
    return path


@settings(max_examples=200, deadline=None)
@given(grids(), st.integers(0, 30))
def test_obstacles_grown_row_by_row_are_those_grown_offset_by_offset(
    window: tuple[Bools, Floats, tuple[int, int], tuple[int, int]], cells: int
) -> None:
    occupied = window[0]
    cells = min(cells, *occupied.shape)  # (the reference's slices need a grid that wide)
    assert np.array_equal(grid._grow(occupied, cells), ref_grow(occupied, cells))


@both_paths
@settings(max_examples=300, deadline=None)
@given(grids())
def test_the_wavefront_is_the_relaxations_to_the_bit(
    kind: str, window: tuple[Bools, Floats, tuple[int, int], tuple[int, int]]
) -> None:
    blocked, cost, goal, _ = window
    with chosen(kind):
        fast = grid._wavefront(blocked, cost, *goal)
    assert np.array_equal(fast, ref_wavefront(blocked, cost, *goal))


@settings(max_examples=300, deadline=None)
@given(grids())
def test_the_compiled_wavefront_stops_with_every_cell_as_numpys(
    window: tuple[Bools, Floats, tuple[int, int], tuple[int, int]],
) -> None:
    """Stopped at the start, the cells not final yet too: the same buckets, bit for bit."""
    blocked, cost, goal, start = window
    with chosen("numpy"):
        plain = grid._wavefront(blocked, cost, *goal, start=start)
    with chosen("numba"):
        compiled = grid._wavefront(blocked, cost, *goal, start=start)
    assert plain.tobytes() == compiled.tobytes()


@both_paths
@settings(max_examples=300, deadline=None)
@given(grids())
def test_stopping_at_the_start_keeps_every_cost_the_way_down_reads(
    kind: str, window: tuple[Bools, Floats, tuple[int, int], tuple[int, int]]
) -> None:
    blocked, cost, goal, start = window
    with chosen(kind):
        fast = grid._wavefront(blocked, cost, *goal, start=start)
    full = ref_wavefront(blocked, cost, *goal)
    assert fast[start] == full[start]
    if full[start] >= grid.UNREACHABLE:
        return
    known = full <= full[start]
    assert np.array_equal(fast[known], full[known])
    assert (fast[~known] > full[start]).all()  # never taken on the way down
    assert _path(fast, start, goal) == _path(full, start, goal)


def _serpentine(size: int) -> Bools:
    """Walls across every other row, the gap at alternate ends: a way of about
    size^2 / 2 moves from one corner to the other."""
    blocked = np.zeros((size, size), dtype=bool)
    for row in range(1, size, 2):
        blocked[row, :] = True
        blocked[row, -1 if row % 4 == 1 else 0] = False
    return blocked


@both_paths
def test_a_way_longer_than_the_relaxations_sweeps_gets_what_they_reached(kind: str) -> None:
    blocked = _serpentine(40)  # 8 (40 + 40) = 640 sweeps, a way of ~800 moves
    cost = np.ones(blocked.shape)
    goal, start = (0, 0), (39, 0)
    reference = ref_wavefront(blocked, cost, *goal)
    assert reference[start] >= grid.UNREACHABLE  # the relaxation stopped short of it
    with chosen(kind):
        assert np.array_equal(grid._wavefront(blocked, cost, *goal), reference)
        fast = grid._wavefront(blocked, cost, *goal, start=start)
    assert np.array_equal(fast, reference)


# --- whole plans and updates over random maps --------------------------------------------


@st.composite
def maps(draw: st.DrawFn) -> OccupancyMap:
    """A small map (16 m across) with random obstacle evidence."""
    m = OccupancyMap(Vec2(0.0, 0.0), half_size_m=8.0)
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    density = draw(st.floats(0.0, 0.35))
    m.evidence[:] = np.where(rng.random(m.evidence.shape) < density, grid.MAX_EVIDENCE, 0)
    return m


coordinates = st.floats(-8.5, 8.5, allow_nan=False)


@both_paths
@settings(max_examples=200, deadline=None)
@given(
    maps(),
    coordinates,
    coordinates,
    coordinates,
    coordinates,
    st.sampled_from([0.0, 0.5, 1.0]),
    st.sampled_from([0.0, 1.0, 2.0]),
    st.sampled_from([0.0, 0.4, 0.9, 1.6]),
)
def test_a_plan_is_the_plain_plans(
    kind: str,
    m: OccupancyMap,
    x0: float,
    y0: float,
    x1: float,
    y1: float,
    keep_off_m: float,
    ahead_m: float,
    footprint_m: float,
) -> None:
    start, goal = Vec2(x0, y0), Vec2(x1, y1)
    kwargs = {"keep_off_m": keep_off_m, "ahead_m": ahead_m, "footprint_m": footprint_m}
    with chosen(kind):
        planned = m.plan(start, goal, **kwargs)
    assert planned == ref_plan(m, start, goal, **kwargs)
    assert planned is None or planned.length_m >= m.fewest_m(start, goal)  # none comes under


@settings(max_examples=200, deadline=None)
@given(maps(), coordinates, coordinates, coordinates, coordinates, st.sampled_from([0.0, 0.9, 1.6]))
def test_a_routes_length_is_the_plain_plans(
    m: OccupancyMap, x0: float, y0: float, x1: float, y1: float, footprint_m: float
) -> None:
    start, goal = Vec2(x0, y0), Vec2(x1, y1)
    planned = ref_plan(m, start, goal, keep_off_m=0.0, ahead_m=2.0, footprint_m=footprint_m)
    want = None if planned is None else planned[1]
    length_m = m.route_length_m(start, goal, footprint_m=footprint_m)
    assert length_m == want
    assert length_m is None or length_m >= m.fewest_m(start, goal)  # none comes under


@settings(max_examples=100, deadline=None)
@given(coordinates, coordinates, coordinates, coordinates, st.sampled_from([0.0, 0.9, 1.6]))
def test_on_an_open_map_a_route_is_the_fewest_moves(
    x0: float, y0: float, x1: float, y1: float, footprint_m: float
) -> None:
    """Every route is at least `fewest_m` long (the two tests above); with nothing in the
    way one is that long, to the hair."""
    m = OccupancyMap(Vec2(0.0, 0.0), half_size_m=8.0)
    start, goal = Vec2(x0, y0), Vec2(x1, y1)
    length_m = m.route_length_m(start, goal, footprint_m=footprint_m)
    assert length_m is None or length_m == pytest.approx(m.fewest_m(start, goal), rel=1e-8)


@both_paths
@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans())
def test_updates_leave_the_map_the_plain_updates_leave(
    kind: str, seed: int, odd_evidence: bool
) -> None:
    """A run of random readings, from a map blank or holding any byte (as code writing
    `evidence` directly may leave it)."""
    rng = np.random.default_rng(seed)
    fast, plain = OccupancyMap(Vec2(0.0, 0.0)), OccupancyMap(Vec2(0.0, 0.0))
    if odd_evidence:
        fast.evidence[:] = plain.evidence[:] = rng.integers(-128, 128, fast.evidence.shape)
    units = SONAR.unit_x_m.size
    for _ in range(20):
        x_m, y_m, theta_rad = (
            rng.uniform(-45.0, 45.0),
            rng.uniform(-45.0, 45.0),
            rng.uniform(-4.0, 4.0),
        )
        pose = Pose2D(float(x_m), float(y_m), float(theta_rad))
        ranges = np.where(rng.random(units) < 0.3, 5.0, rng.uniform(0.0, 5.0, units))
        echo = rng.random(units) < 0.7
        with chosen(kind):
            fast.update(pose, SONAR, ranges, echo)
        ref_update(plain, pose, ranges, echo)
        assert np.array_equal(fast.evidence, plain.evidence)
        assert np.array_equal(fast.seen, plain.seen)


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([-1, 3, 6, -7]))
def test_adding_points_is_the_plain_add(seed: int, amount: int) -> None:
    rng = np.random.default_rng(seed)
    fast, plain = OccupancyMap(Vec2(0.0, 0.0)), OccupancyMap(Vec2(0.0, 0.0))
    fast.evidence[:] = plain.evidence[:] = rng.integers(-128, 128, fast.evidence.shape)
    x, y = rng.uniform(-45.0, 45.0, (2, 200))
    x[:50] = x[50:100]  # points falling in the same cells
    fast._add(x, y, amount)
    ref_add(plain, x, y, amount)
    assert np.array_equal(fast.evidence, plain.evidence)
    assert np.array_equal(fast.seen, plain.seen)


# --- the fleet's map: every scan of a batch at once ----------------------------------------

ROBOTS = ("r1", "r2", "r3")


def ref_robot_echo(scan: Scan, unit: int, robot: Vec2) -> bool:
    """Whether the echo of the scan's transducer `unit` is `robot` (world frame): the
    point of its arc nearest the robot, one transducer at a time in floats."""
    at = scan.pose.to_body(robot)
    ux, uy = float(SONAR.unit_x_m[unit]), float(SONAR.unit_y_m[unit])
    heading = float(SONAR.unit_heading_rad[unit])
    off = math.remainder(math.atan2(at.y_m - uy, at.x_m - ux) - heading, 2.0 * math.pi)
    off = min(max(off, -float(SONAR.reach_right_rad[unit])), float(SONAR.reach_left_rad[unit]))
    r = scan.ranges_m[unit]
    nearest = Vec2(ux + r * math.cos(heading + off), uy + r * math.sin(heading + off))
    return (nearest - at).norm() < SONAR.radius_m + fleet_map.FLEET_MASK_M


def ref_fleet_add(
    m: OccupancyMap, added: dict[str, float], at: dict[str, Scan], scans: list[Scan]
) -> tuple[int, int]:
    """The scans not added yet, one plain update each (oldest first, then the robots'
    order), each echo that another robot's latest scan (`at`, kept up to date here)
    puts on its arc left out; how many scans were added, and how many echoes left out."""
    rank = {r: i for i, r in enumerate(ROBOTS)}
    fresh = [s for s in scans if s.stamp_s > added.get(s.robot_id, -np.inf) and s.ranges_m]
    fresh.sort(key=lambda s: (s.stamp_s, rank.get(s.robot_id, len(rank))))
    for scan in fresh:
        if scan.robot_id not in at or scan.stamp_s >= at[scan.robot_id].stamp_s:
            at[scan.robot_id] = scan
    count = dropped = 0
    for scan in fresh:
        if scan.stamp_s <= added.get(scan.robot_id, -np.inf):
            continue
        echo = list(scan.echo)
        if len(scan.ranges_m) == SONAR.unit_x_m.size:
            others = [
                Vec2(o.x_m, o.y_m)
                for o in at.values()
                if o.robot_id != scan.robot_id
                and abs(o.stamp_s - scan.stamp_s) <= fleet_map.FLEET_FRESH_S
            ]
            for unit, heard in enumerate(echo):
                if heard and any(ref_robot_echo(scan, unit, o) for o in others):
                    echo[unit] = False
                    dropped += 1
        ref_update(m, scan.pose, np.asarray(scan.ranges_m), np.asarray(echo, dtype=bool))
        added[scan.robot_id] = scan.stamp_s
        count += 1
    return count, dropped


def _scan(
    rng: np.random.Generator, robot: str, stamp_s: float, units: int = 16, spread_m: float = 10.0
) -> Scan:
    ranges = np.where(rng.random(units) < 0.3, 5.0, rng.uniform(0.1, 5.0, units))
    return Scan(
        robot,
        stamp_s,
        float(rng.uniform(-spread_m, spread_m)),
        float(rng.uniform(-spread_m, spread_m)),
        float(rng.uniform(-3.0, 3.0)),
        tuple(ranges.tolist()),
        tuple((rng.random(units) < 0.7).tolist()),
    )


@both_paths
@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_the_fleets_batches_leave_the_map_one_plain_update_a_scan_leaves(
    kind: str, seed: int
) -> None:
    """Batches of scans of three robots a few metres apart (echoes of one another among
    them), stamps repeating (stale scans, two of one robot in a batch), some rings short."""
    rng = np.random.default_rng(seed)
    fleet = FleetMap(Vec2(0.0, 0.0), sonar=SONAR, order=ROBOTS)
    plain, count, dropped = OccupancyMap(Vec2(0.0, 0.0)), 0, 0
    added: dict[str, float] = {}
    at: dict[str, Scan] = {}
    for _ in range(8):
        scans = [
            _scan(
                rng,
                str(rng.choice(ROBOTS)),
                float(rng.integers(0, 6)),
                8 if rng.random() < 0.1 else 16,
                spread_m=2.0,
            )
            for _ in range(int(rng.integers(0, 6)))
        ]
        with chosen(kind):
            fleet.add(scans)
        scans_added, echoes_left_out = ref_fleet_add(plain, added, at, scans)
        count, dropped = count + scans_added, dropped + echoes_left_out
        assert np.array_equal(fleet.map.evidence, plain.evidence)
        assert np.array_equal(fleet.map.seen, plain.seen)
        assert fleet.added == added
        assert fleet.scans_added == count
        assert fleet.robot_echoes == dropped


@both_paths
def test_a_scan_the_map_cannot_take_leaves_the_earlier_ones_added(kind: str) -> None:
    """A ring longer than the robot's, its echoes one per range: it raises, as adding it
    alone does, after the scans before it are in (and counted), before those after it."""
    rng = np.random.default_rng(7)
    first, odd, last = _scan(rng, "r1", 1.0), _scan(rng, "r2", 2.0, 24), _scan(rng, "r3", 3.0)
    fleet = FleetMap(Vec2(0.0, 0.0), sonar=SONAR, order=ROBOTS)
    with pytest.raises(ValueError, match="broadcast"), chosen(kind):
        fleet.add([last, odd, first])
    plain = OccupancyMap(Vec2(0.0, 0.0))
    ref_update(plain, first.pose, np.asarray(first.ranges_m), np.asarray(first.echo))
    assert np.array_equal(fleet.map.evidence, plain.evidence)
    assert fleet.added == {"r1": 1.0}
    assert fleet.scans_added == 1
    with pytest.raises(ValueError, match="broadcast"):
        OccupancyMap(Vec2(0.0, 0.0)).update(odd.pose, SONAR, odd.ranges_m, np.asarray(odd.echo))
