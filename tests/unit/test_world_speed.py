"""The simulated world's fast paths give what the plain code they replace gave, bit for
bit: the sonar cast (every ray against the discs each robot hears, in a block; the walls
no robot can hear left out) against the cast as it was (only the rays pointing towards
each disc, every wall edge), a world step among walls (sub-steps without contact checks
when no robot is near a polygon's bounding box, and the polygons checked only for the
robots near one) against checking every polygon for every robot at every sub-step, and
the plain-float checks of a few robots against numpy's. The plain cast is kept here, as
it was, as the reference (its circle and segment arithmetic `circle_hits_at` and
`ray_segment_hits`, from lab/plain_rays.py; the leaner segment test is held to the
latter).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from hypothesis import given, settings
from hypothesis import strategies as st
from plain_rays import ray_segment_hits

from phalanx.core.config import CircleObstacle, NoiseConfig, PolygonObstacle, WorldConfig
from phalanx.core.config_files import load_robot
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.simulator import contacts as contacts_module
from phalanx.simulator import pairs
from phalanx.simulator.contacts import Contacts, polygon_edges
from phalanx.simulator.pairs import close_pairs
from phalanx.simulator.sonar import (
    circle_hits_at,
    nearest_segment_hits,
    per_unit,
    rays_towards,
    ring_rays,
)
from phalanx.simulator.world import World

ROBOT = load_robot("p3dx")
Floats = npt.NDArray[np.float64]
Ints = npt.NDArray[np.intp]


# --- the reference: the cast as it was -----------------------------------------------------


def plain_discs(world: World, idx: Ints) -> tuple[Ints, Floats, Floats, Floats]:
    """(row of idx, centre x, y, radius) of the discs robots `idx` may hear: the circles
    within the sonar's reach plus 1 m and 50 noise sigmas, the robots within reach.
    """
    ring, scene = world.ring, world.scene
    x_all, y_all = world.x, world.y
    x, y = x_all[idx], y_all[idx]
    circles = world._circles
    horizon = ring.max_range_m + ring.mount_m + 1.0 + 50.0 * scene.sonar_std_m
    d = np.hypot(x[:, None] - circles[:, 0], y[:, None] - circles[:, 1])
    ri, k = np.nonzero(d - circles[:, 2] < horizon)
    rows, cx, cy, r = [ri], [circles[k, 0]], [circles[k, 1]], [circles[k, 2]]
    if idx.size == x_all.size:
        ri, j = close_pairs(x_all, y_all, ring.max_range_m + ROBOT.radius_m + 0.5)
    else:
        ri, j = np.nonzero(np.ones((idx.size, x_all.size), dtype=bool))
        ri, j = ri[j != idx[ri]], j[j != idx[ri]]
    near = np.hypot(x_all[j] - x[ri], y_all[j] - y[ri]) < ring.max_range_m + ROBOT.radius_m + 0.5
    rows.append(ri[near])
    cx.append(x_all[j[near]])
    cy.append(y_all[j[near]])
    r.append(np.full(int(near.sum()), ROBOT.radius_m))
    cat = np.concatenate
    return cat(rows), cat(cx), cat(cy), cat(r)


def plain_cast(world: World, idx: Ints) -> Floats:
    """Robots `idx`'s sonar ranges: each disc against the rays pointing towards it,
    every ray against every wall edge, noise from the world's stream, clipped.
    """
    ring = world.ring
    x, y, th = world.x, world.y, world.th
    rays = ring_rays(ring, x[idx], y[idx], th[idx])
    owner, cx, cy, r = plain_discs(world, idx)
    ox_, oy_, oth = x[idx][owner], y[idx][owner], th[idx][owner]
    bearing = np.arctan2(cy - oy_, cx - ox_) - oth
    pair, ray = rays_towards(ring, bearing, np.hypot(cx - ox_, cy - oy_), r)
    flat = owner[pair] * ring.angle_rad.size + ray
    ox, oy, dx, dy = (a.ravel()[flat] for a in rays)
    nearest = np.full(rays[0].size, np.inf)
    np.minimum.at(nearest, flat, circle_hits_at(ox, oy, dx, dy, cx[pair], cy[pair], r[pair]))
    hits = nearest.reshape(rays[0].shape)
    e = world._edges
    if e.ax.size:
        ox, oy, dx, dy = (a.ravel() for a in rays)
        walls = ray_segment_hits(ox, oy, dx, dy, e.ax, e.ay, e.bx, e.by)
        hits = np.minimum(hits, walls.reshape(hits.shape))
    ranges = per_unit(ring, hits)
    if world.scene.sonar_std_m > 0.0:
        ranges = ranges + world.rng.normal(0.0, world.scene.sonar_std_m, ranges.shape)
    return np.asarray(np.clip(ranges, ring.min_range_m, ring.max_range_m), dtype=np.float64)


# --- worlds --------------------------------------------------------------------------------

coords = st.floats(-9.0, 9.0, allow_nan=False)
circles = st.lists(
    st.builds(lambda x, y, r: CircleObstacle(x_m=x, y_m=y, radius_m=r), coords, coords,
              st.floats(0.05, 1.5)),
    max_size=10,
)  # fmt: skip


@st.composite
def polygons(draw: st.DrawFn) -> tuple[PolygonObstacle, ...]:
    """Walls: thin boxes along the axes, a few tilted triangles, and a concave V."""
    out = []
    for _ in range(draw(st.integers(0, 3))):
        x0, y0 = draw(coords), draw(coords)
        if draw(st.booleans()):
            w, h = draw(st.floats(0.05, 12.0)), draw(st.floats(0.05, 12.0))
            pts = ((x0, y0), (x0 + w, y0), (x0 + w, y0 + h), (x0, y0 + h))
        else:
            pts = ((x0, y0), (draw(coords), draw(coords)), (draw(coords), draw(coords)))
        out.append(PolygonObstacle(vertices_m=pts))
    if draw(st.booleans()):
        x, y = draw(coords), draw(coords)
        v = ((x, y), (x - 1.4, y + 1.4), (x - 1.3, y + 1.4), (x + 0.1, y), (x - 1.3, y - 1.4))
        out.append(PolygonObstacle(vertices_m=(*v, (x - 1.4, y - 1.4))))
    return tuple(out)


def world_of(
    config: WorldConfig, poses: list[tuple[float, float, float]], *, sonar_std_m: float, seed: int
) -> World:
    world = World(robot=ROBOT, world=config, noise=NoiseConfig(sonar_std_m=sonar_std_m), seed=seed)
    for i, (x, y, th) in enumerate(poses):
        world.add_robot(f"r{i}", Pose2D(x, y, th))
    return world


poses = st.lists(st.tuples(coords, coords, st.floats(-math.pi, math.pi)), min_size=1, max_size=9)
noise = st.sampled_from([0.0, 0.0, 0.02, 0.3])


@settings(max_examples=150, deadline=None)
@given(circles, polygons(), poses, noise, st.integers(0, 2**16))
def test_the_cast_is_the_plain_cast(
    c: list[CircleObstacle],
    walls: tuple[PolygonObstacle, ...],
    at: list[tuple[float, float, float]],
    sonar_std_m: float,
    seed: int,
) -> None:
    config = WorldConfig(circles=tuple(c), polygons=walls)
    fast, plain = (world_of(config, at, sonar_std_m=sonar_std_m, seed=seed) for _ in "ab")
    assert fast.sense_all().tobytes() == plain_cast(plain, np.arange(len(at))).tobytes()
    # one robot at a time, as `World.status` casts without a batch runner
    for i in range(len(at)):
        one = np.array([i])
        ours = fast.scene.cast(fast.x, fast.y, fast.th, one)
        assert ours.tobytes() == plain_cast(plain, one).tobytes()


@settings(max_examples=150, deadline=None)
@given(circles, poses, st.sampled_from([0.0, 0.3]))
def test_every_ray_against_the_discs_heard_is_only_the_rays_towards_them(
    c: list[CircleObstacle], at: list[tuple[float, float, float]], sonar_std_m: float
) -> None:
    world = world_of(WorldConfig(circles=tuple(c)), at, sonar_std_m=sonar_std_m, seed=0)
    scene, x, y, th = world.scene, world.x, world.y, world.th
    for idx in (np.arange(len(at)), np.array([len(at) - 1])):
        rays = ring_rays(world.ring, x[idx], y[idx], th[idx])
        block = scene._hits_every_ray(x, y, idx, (x[idx], y[idx]), rays)
        # (equal values: a hit of 0 may come out -0 either way, which the clip removes)
        assert np.array_equal(block, scene._hits_towards(x, y, th, idx, rays))


angles = st.floats(-math.pi, math.pi) | st.sampled_from([0.0, math.pi / 2, math.pi, -math.pi / 2])


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.tuples(coords, coords, angles), min_size=1, max_size=12),
    st.lists(st.tuples(coords, coords, coords, coords), min_size=1, max_size=8),
)
def test_nearest_segment_hits_is_ray_segment_hits(
    rays: list[tuple[float, float, float]], segments: list[tuple[float, float, float, float]]
) -> None:
    ox, oy, a = (np.array(c, dtype=np.float64) for c in zip(*rays, strict=True))
    ax, ay, bx, by = (np.array(c, dtype=np.float64) for c in zip(*segments, strict=True))
    # along the axes and along the segments themselves too: parallel pairs
    dirs = [(np.cos(a), np.sin(a)), (np.ones_like(a), np.zeros_like(a))]
    dirs += [(np.full_like(a, bx[0] - ax[0]), np.full_like(a, by[0] - ay[0]))]
    for dx, dy in dirs:
        plain = ray_segment_hits(ox, oy, dx, dy, ax, ay, bx, by)
        ours = nearest_segment_hits(ox, oy, dx, dy, ax, ay, bx - ax, by - ay)
        assert ours.tobytes() == plain.tobytes()


# --- stepping among walls ------------------------------------------------------------------


def _everyone_near_walls(world: World) -> None:
    """The plain stepping: every robot's polygons checked at every sub-step (as if every
    robot were near a wall), so no step with polygons glides.
    """
    world.contacts.near_walls = (  # type: ignore[method-assign]
        lambda x, y, radius, travel_m: list(range(len(x))) if world.config.polygons else []
    )


def _drive(world: World, seed: int, ticks: int) -> tuple[int, int]:
    """`ticks` of random commands, fast enough to reach the walls: (glided, checked)."""
    rng = np.random.default_rng(seed)
    glided = checked = 0
    for _ in range(ticks):
        commands = {
            rid: Twist2D(float(rng.uniform(-0.3, 1.2)), float(rng.uniform(-1.5, 1.5)))
            for rid in world.robot_ids
        }
        free = world._contact_free(0.1)
        glided, checked = glided + free, checked + (not free)
        world.step(commands, 0.1)
    return glided, checked


def _same(fast: World, plain: World) -> None:
    for name in ("x", "y", "th", "v", "w", "odo", "bumped"):
        assert getattr(fast, name).tobytes() == getattr(plain, name).tobytes(), name
    assert fast.collisions == plain.collisions


@settings(max_examples=60, deadline=None)
@given(circles, polygons(), poses, st.integers(0, 2**16))
def test_stepping_among_walls_is_the_plain_stepping(
    c: list[CircleObstacle],
    walls: tuple[PolygonObstacle, ...],
    at: list[tuple[float, float, float]],
    seed: int,
) -> None:
    config = WorldConfig(circles=tuple(c), polygons=walls)
    fast, plain = (world_of(config, at, sonar_std_m=0.0, seed=seed) for _ in "ab")
    _everyone_near_walls(plain)
    _drive(fast, seed, 40)
    _drive(plain, seed, 40)
    _same(fast, plain)


def test_a_fleet_driven_into_walls_glides_checks_and_collides_as_the_plain_one() -> None:
    walls = (
        PolygonObstacle(vertices_m=((-6.0, 4.0), (30.0, 4.0), (30.0, 4.3), (-6.0, 4.3))),
        PolygonObstacle(vertices_m=((-6.0, -4.3), (30.0, -4.3), (30.0, -4.0), (-6.0, -4.0))),
        PolygonObstacle(vertices_m=((6.0, 1.0), (5.0, 2.0), (5.1, 2.0), (6.1, 1.0), (5.1, 0.0),
                                    (5.0, 0.0))),
    )  # fmt: skip
    config = WorldConfig(circles=(CircleObstacle(x_m=3.0, y_m=-1.5, radius_m=0.4),), polygons=walls)
    at = [(0.0, 0.0, 0.3), (-1.0, 1.5, 1.2), (-1.0, -1.5, -1.0), (-2.0, 0.0, 0.0)]
    fast, plain = (world_of(config, at, sonar_std_m=0.0, seed=5) for _ in "ab")
    _everyone_near_walls(plain)
    glided, checked = _drive(fast, 11, 300)
    plain_glided, _ = _drive(plain, 11, 300)
    _same(fast, plain)
    assert glided  # both paths taken
    assert checked
    assert plain_glided == 0  # (the plain stepping never glides among walls)
    walls_hit = {c.other for c in fast.collisions} & {"obstacle:1", "obstacle:2", "obstacle:3"}
    assert walls_hit  # (obstacle:0 is the circle)


# --- a few robots in plain floats ----------------------------------------------------------

spots = st.lists(st.tuples(coords, coords), min_size=0, max_size=14)


@settings(max_examples=300, deadline=None)
@given(polygons(), spots, st.floats(0.0, 0.5))
def test_near_walls_in_floats_is_numpys_and_leaves_out_only_robots_clear_of_walls(
    walls: tuple[PolygonObstacle, ...], at: list[tuple[float, float]], travel_m: float
) -> None:
    config = WorldConfig(polygons=walls)
    edges = polygon_edges(config)
    contacts = Contacts(config, np.zeros((0, 3)), edges, [f"r{i}" for i in range(len(at))])
    x = np.array([p[0] for p in at], dtype=np.float64)
    y = np.array([p[1] for p in at], dtype=np.float64)
    radius = ROBOT.radius_m
    near = contacts.near_walls(x, y, radius, travel_m)
    floats = contacts._near_boxes(x.tolist(), y.tolist(), radius + travel_m + 1e-6)
    assert near == floats
    saved, contacts_module._FEW_ROBOTS = contacts_module._FEW_ROBOTS, -1
    try:
        assert contacts.near_walls(x, y, radius, travel_m) == near  # numpy's
    finally:
        contacts_module._FEW_ROBOTS = saved
    for i in set(range(len(at))) - set(near):
        px, py = float(x[i]), float(y[i])
        if edges.ax.size:
            gap = contacts_module._segment_distance(px, py, edges).min()
            assert gap > radius + travel_m
        for poly in walls:
            assert not contacts_module._inside_polygon(px, py, poly.vertices_m)


@settings(max_examples=300, deadline=None)
@given(spots, st.floats(0.0, 3.0))
def test_any_pair_within_in_floats_is_numpys(at: list[tuple[float, float]], d: float) -> None:
    x = np.array([p[0] for p in at], dtype=np.float64)
    y = np.array([p[1] for p in at], dtype=np.float64)
    ours = pairs.any_pair_within(x, y, d)
    saved, pairs._FEW = pairs._FEW, -1
    try:
        assert pairs.any_pair_within(x, y, d) == ours  # numpy's matrix
    finally:
        pairs._FEW = saved
    if len(at) >= 2:  # and either is the exact answer, but for a hair's width of rounding
        gaps = [math.hypot(a[0] - b[0], a[1] - b[1]) for k, a in enumerate(at) for b in at[k + 1 :]]
        if abs(min(gaps) - d) > 1e-6:
            assert ours == (min(gaps) < d)
