"""The simulated world: ground truth of every robot, obstacles, sonar, collisions,
odometry (with optional seeded noise) and scripted sensor events.

Robot state lives in numpy arrays (one entry per robot) so a step of 1000 robots is a
handful of vector operations (a fleet of a few robots is stepped in plain floats, which
is faster there and gives the same numbers). Sonar is cast for every robot in one
vectorised pass (`sense_all`), or lazily per robot, against only the obstacles and
robots within sonar range (found through a uniform grid once the fleet is large).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from phalanx.core.config import NoiseConfig, RobotParams, Scenario, SensorEvent, WorldConfig
from phalanx.core.geometry import Pose2D, Twist2D, Vec2
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.core.runlog import Collision
from phalanx.core.scenarios import resolve_world
from phalanx.simulator.kinematics import (
    SCALAR_MAX,
    apply_robot_limits,
    integrate_arcs,
    limits_and_arcs_scalar,
)
from phalanx.simulator.sonar import (
    SonarRing,
    circle_hits_at,
    per_unit,
    ray_segment_hits,
    rays_towards,
    ring_rays,
)

FloatArray = npt.NDArray[np.float64]
_GRID_CELL_M = 1.0
CONTACT_RELEASE_M = 0.05


@dataclass(frozen=True)
class _Edges:
    ax: FloatArray
    ay: FloatArray
    bx: FloatArray
    by: FloatArray
    owner: npt.NDArray[np.intp]  # polygon index of each edge


def _polygon_edges(world: WorldConfig) -> _Edges:
    ax, ay, bx, by, owner = [], [], [], [], []
    for i, poly in enumerate(world.polygons):
        pts = poly.vertices_m
        for (x0, y0), (x1, y1) in zip(pts, pts[1:] + pts[:1], strict=True):
            ax.append(x0)
            ay.append(y0)
            bx.append(x1)
            by.append(y1)
            owner.append(i)
    arr = np.array
    return _Edges(
        arr(ax, float), arr(ay, float), arr(bx, float), arr(by, float), arr(owner, dtype=np.intp)
    )


def _inside_polygon(px: float, py: float, pts: Sequence[tuple[float, float]]) -> bool:
    inside = False
    for (x0, y0), (x1, y1) in zip(pts, [*pts[1:], pts[0]], strict=True):
        if (y0 > py) != (y1 > py) and px < x0 + (py - y0) * (x1 - x0) / (y1 - y0):
            inside = not inside
    return inside


def _segment_distance(px: float, py: float, e: _Edges) -> FloatArray:
    ex, ey = e.bx - e.ax, e.by - e.ay
    length2 = np.maximum(ex * ex + ey * ey, 1e-12)
    t = np.clip(((px - e.ax) * ex + (py - e.ay) * ey) / length2, 0.0, 1.0)
    return np.asarray(np.hypot(e.ax + t * ex - px, e.ay + t * ey - py), dtype=np.float64)


# Up to this many robots, distances are checked pair by pair (a dense matrix); beyond,
# through a uniform grid.
_PAIRWISE_MAX = 64
# A disc further than this beyond the sonar's reach is left out of the cast: its echo
# could only come back shorter than max range through noise of over 1 m (50 sigma and more).
_CAST_MARGIN_M = 1.0
_CAST_MARGIN_SIGMAS = 50.0
# Rays x discs (or edges) worked out at once, to bound memory on large fleets.
_CHUNK = 1 << 18


def _grid_pairs(
    ax: FloatArray, ay: FloatArray, bx: FloatArray, by: FloatArray, cell_m: float
) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """(i, j) of every point a_i and b_j in the same or neighbouring cells of a grid of
    `cell_m`: a superset of the pairs closer than `cell_m`, sorted by i.
    """
    kax, kay = np.floor(ax / cell_m).astype(np.int64), np.floor(ay / cell_m).astype(np.int64)
    kbx, kby = np.floor(bx / cell_m).astype(np.int64), np.floor(by / cell_m).astype(np.int64)
    x0 = min(int(kax.min()), int(kbx.min())) - 1
    y0 = min(int(kay.min()), int(kby.min())) - 1
    width = max(int(kay.max()), int(kby.max())) - y0 + 2
    keys = (kbx - x0) * width + (kby - y0)
    order = np.argsort(keys, kind="stable")
    ordered = keys[order]
    firsts, lasts = [], []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            q = (kax + dx - x0) * width + (kay + dy - y0)
            firsts.append(np.searchsorted(ordered, q, "left"))
            lasts.append(np.searchsorted(ordered, q, "right"))
    lo, hi = np.stack(firsts, axis=1).ravel(), np.stack(lasts, axis=1).ravel()
    counts = hi - lo
    total = int(counts.sum())
    i = np.repeat(np.repeat(np.arange(ax.size), 9), counts)
    start = np.repeat(lo - (np.cumsum(counts) - counts), counts)
    return i, order[start + np.arange(total)]


def _close_pairs(
    x: FloatArray, y: FloatArray, distance_m: float
) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """(i, j), i != j, of every two robots whose centres may lie within `distance_m`
    (every pair of a small fleet; grid neighbours of a large one), sorted by i.
    """
    n = x.size
    if n <= _PAIRWISE_MAX:
        i, j = np.nonzero(~np.eye(n, dtype=bool))
        return i, j
    i, j = _grid_pairs(x, y, x, y, distance_m)
    keep = i != j
    return i[keep], j[keep]


def _any_pair_within(x: FloatArray, y: FloatArray, distance_m: float) -> bool:
    """Whether any two of the points (x, y) lie closer than `distance_m`."""
    if len(x) < 2:
        return False
    # a hair wide of the grid's exact hypot test: never misses a contact it would find
    limit = (distance_m * (1.0 + 1e-9)) ** 2
    if len(x) <= _PAIRWISE_MAX:
        d2 = (x[:, None] - x[None, :]) ** 2 + (y[:, None] - y[None, :]) ** 2
        np.fill_diagonal(d2, np.inf)
        return bool(d2.min() < limit)
    i, j = _close_pairs(x, y, 2.0 * distance_m)
    return bool(np.any((x[i] - x[j]) ** 2 + (y[i] - y[j]) ** 2 < limit))


class World:
    """Ground truth and sensing for a group of identical robots."""

    def __init__(
        self,
        *,
        robot: RobotParams,
        world: WorldConfig,
        noise: NoiseConfig,
        events: Sequence[SensorEvent] = (),
        seed: int = 0,
    ) -> None:
        world = resolve_world(world)  # a seeded field becomes plain circles
        self.robot, self.config, self.noise, self.events = robot, world, noise, tuple(events)
        self.rng = np.random.default_rng(seed)
        self.ring = SonarRing.from_params(robot.sonar)
        self.t_s = 0.0
        self.collisions: list[Collision] = []
        self._ids: list[str] = []
        self._index: dict[str, int] = {}
        z = np.zeros(0)
        self.x, self.y, self.th, self.v, self.w = z, z.copy(), z.copy(), z.copy(), z.copy()
        self.v_cmd, self.w_cmd = z.copy(), z.copy()
        self.odo = np.zeros((0, 3))
        self.bumped = np.zeros(0, dtype=bool)
        self._contacts: set[tuple[str, str]] = set()
        self._circles = np.array([(c.x_m, c.y_m, c.radius_m) for c in world.circles]).reshape(-1, 3)
        self._edges = _polygon_edges(world)
        self._sonar_cache: dict[int, FloatArray] = {}
        self._ranges: FloatArray | None = None  # every robot's, when cast in one pass

    @classmethod
    def for_scenario(cls, scenario: Scenario, robot: RobotParams) -> World:
        """The scenario's world with every robot at its start pose."""
        world = cls(
            robot=robot,
            world=scenario.world,
            noise=scenario.noise,
            events=scenario.events,
            seed=scenario.seed,
        )
        for entry in scenario.robots:
            world.add_robot(entry.id, scenario.start_pose(entry.id))
        return world

    @property
    def robot_ids(self) -> tuple[str, ...]:
        """Every robot, in the order added."""
        return tuple(self._ids)

    def add_robot(self, robot_id: str, pose: Pose2D) -> None:
        """Place a robot at rest at `pose`."""
        if robot_id in self._index:
            raise ValueError(f"robot {robot_id!r} is already in the world")
        self._index[robot_id] = len(self._ids)
        self._ids.append(robot_id)
        app = np.append
        self.x, self.y, self.th = (
            app(self.x, pose.x_m),
            app(self.y, pose.y_m),
            app(self.th, pose.theta_rad),
        )
        self.v, self.w = app(self.v, 0.0), app(self.w, 0.0)
        self.v_cmd, self.w_cmd = app(self.v_cmd, 0.0), app(self.w_cmd, 0.0)
        self.odo = np.vstack([self.odo, [pose.x_m, pose.y_m, pose.theta_rad]])
        self.bumped = app(self.bumped, False)

    # --- motion ------------------------------------------------------------------------

    def step(self, commands: Mapping[str, Twist2D], dt_s: float) -> None:
        """Advance `dt_s`: robots chase their commands within limits, in sub-steps."""
        for rid, cmd in commands.items():
            i = self._index[rid]
            self.v_cmd[i], self.w_cmd[i] = cmd.v_mps, cmd.omega_radps
        sub = dt_s / self.config.substeps
        self.bumped[:] = False
        for _ in range(self.config.substeps):
            self._substep(sub)
        self._update_odometry(dt_s)
        self.t_s += dt_s
        self._sonar_cache.clear()
        self._ranges = None

    def _substep(self, dt_s: float) -> None:
        if len(self._ids) <= SCALAR_MAX:
            self.v, self.w, x, y, th = limits_and_arcs_scalar(
                (self.x, self.y, self.th, self.v, self.w, self.v_cmd, self.w_cmd), self.robot, dt_s
            )
        else:
            self.v, self.w = apply_robot_limits(
                self.v, self.w, self.v_cmd, self.w_cmd, self.robot, dt_s
            )
            x, y, th = integrate_arcs(self.x, self.y, self.th, self.v, self.w, dt_s)
        touching = self._touching(x, y, self.robot.radius_m)
        if not touching:  # the usual case: every robot moves
            self.x, self.y, self.th = x, y, th
        else:
            blocked = np.zeros(len(self._ids), dtype=bool)
            for i, other in touching:
                blocked[i] = True
                self._record_contact(self._ids[i], other)
            keep = ~blocked
            self.x, self.y, self.th = (
                np.where(keep, x, self.x),
                np.where(keep, y, self.y),
                np.where(keep, th, self.th),
            )
            self.v, self.w = np.where(keep, self.v, 0.0), np.where(keep, self.w, 0.0)
            self.bumped |= blocked
        # An episode lasts until the robot has backed CONTACT_RELEASE_M away, so a robot
        # pushing against a wall is one collision, not one per sub-step.
        if self._contacts:  # (none under way, the usual case: nothing to release)
            loose = self._touching(self.x, self.y, self.robot.radius_m + CONTACT_RELEASE_M)
            still = {(self._ids[i], o) for i, o in loose}
            self._contacts &= still
        self._contacts |= {(self._ids[i], o) for i, o in touching}

    def _record_contact(self, rid: str, other: str) -> None:
        if (rid, other) not in self._contacts:
            self.collisions.append(Collision(round(self.t_s, 9), rid, other))

    def _touching(self, x: FloatArray, y: FloatArray, radius: float) -> list[tuple[int, str]]:
        """(robot index, other) for every contact of discs of `radius` at x, y."""
        found: list[tuple[int, str]] = []
        if len(self._circles):
            d = np.hypot(x[:, None] - self._circles[:, 0], y[:, None] - self._circles[:, 1])
            for i, k in zip(*np.nonzero(d < self._circles[:, 2] + radius), strict=True):
                found.append((int(i), f"obstacle:{int(k)}"))
        if self._edges.ax.size:
            found += self._polygon_contacts(x, y, radius)
        found += self._robot_contacts(x, y, radius)
        return found

    def _polygon_contacts(
        self, x: FloatArray, y: FloatArray, radius: float
    ) -> list[tuple[int, str]]:
        found = []
        offset = len(self.config.circles)
        for i in range(len(x)):
            near = _segment_distance(float(x[i]), float(y[i]), self._edges) < radius
            owners = set(self._edges.owner[near].tolist())
            for k, poly in enumerate(self.config.polygons):
                if k in owners or _inside_polygon(float(x[i]), float(y[i]), poly.vertices_m):
                    found.append((i, f"obstacle:{offset + k}"))
        return found

    def _robot_contacts(self, x: FloatArray, y: FloatArray, radius: float) -> list[tuple[int, str]]:
        if not _any_pair_within(x, y, 2 * radius):
            return []  # the usual case, settled without building the grid
        cells: dict[tuple[int, int], list[int]] = {}
        for i, key in enumerate(
            zip(
                (x // _GRID_CELL_M).astype(int).tolist(),
                (y // _GRID_CELL_M).astype(int).tolist(),
                strict=True,
            )
        ):
            cells.setdefault(key, []).append(i)
        found = []
        for (cx, cy), members in cells.items():
            near = [
                j
                for dx in (-1, 0, 1)
                for dy in (-1, 0, 1)
                for j in cells.get((cx + dx, cy + dy), ())
            ]
            for i in members:
                for j in near:
                    if i != j and math.hypot(x[i] - x[j], y[i] - y[j]) < 2 * radius:
                        found.append((i, self._ids[j]))
        return found

    def _update_odometry(self, dt_s: float) -> None:
        n = self.noise
        if n.odometry_v_std_frac == 0.0 and n.odometry_omega_std_radps == 0.0:
            self.odo = np.column_stack([self.x, self.y, self.th])
            return
        v = self.v * (1.0 + self.rng.normal(0.0, n.odometry_v_std_frac, len(self.v)))
        w = self.w + self.rng.normal(0.0, n.odometry_omega_std_radps, len(self.w))
        ox, oy, oth = integrate_arcs(self.odo[:, 0], self.odo[:, 1], self.odo[:, 2], v, w, dt_s)
        self.odo = np.column_stack([ox, oy, oth])

    # --- sensing -----------------------------------------------------------------------

    def truth(self, robot_id: str) -> tuple[Pose2D, Twist2D]:
        """Ground-truth pose and twist."""
        i = self._index[robot_id]
        return (
            Pose2D(float(self.x[i]), float(self.y[i]), float(self.th[i])),
            Twist2D(float(self.v[i]), float(self.w[i])),
        )

    def odometry(self, robot_id: str) -> Odometry:
        """Odometry in the world frame (exact without noise; drifting with it)."""
        i = self._index[robot_id]
        ox, oy, oth = self.odo[i]
        return Odometry(
            Pose2D(float(ox), float(oy), float(oth)),
            Twist2D(float(self.v[i]), float(self.w[i])),
            self.t_s,
        )

    def status(self, robot_id: str) -> RobotStatus:
        """Sonar ranges (events and noise applied), bumpers, motors enabled."""
        i = self._index[robot_id]
        ranges = self._event_ranges(robot_id, self._sonar(i))
        bumper = bool(self.bumped[i]) or self._event_active("bumper", robot_id)
        return RobotStatus(
            sonar_ranges_m=tuple(float(r) for r in ranges), bumpers=(bumper,), motors_enabled=True
        )

    def odometries(self) -> list[Odometry]:
        """Every robot's `odometry`, in the order added."""
        twists = [Twist2D(v, w) for v, w in zip(self.v.tolist(), self.w.tolist(), strict=True)]
        return [
            Odometry(Pose2D(x, y, th), twist, self.t_s)
            for (x, y, th), twist in zip(self.odo.tolist(), twists, strict=True)
        ]

    def statuses(self) -> tuple[list[RobotStatus], FloatArray]:
        """Every robot's `status` (sonar cast for all in one pass), in the order added, and
        their sonar ranges as rows (events applied).
        """
        ranges = self.sense_all()
        if self.events:
            ranges = np.array(
                [self._event_ranges(rid, row) for rid, row in zip(self._ids, ranges, strict=True)]
            )
        bumped = self.bumped.tolist()
        out = []
        for i, (rid, row) in enumerate(zip(self._ids, ranges.tolist(), strict=True)):
            bumper = bumped[i] or (bool(self.events) and self._event_active("bumper", rid))
            out.append(
                RobotStatus(sonar_ranges_m=tuple(row), bumpers=(bumper,), motors_enabled=True)
            )
        return out, ranges

    def sonar_rays(self, robot_id: str) -> list[tuple[Vec2, Vec2]]:
        """(origin, end) of each transducer's centre ray in the world, for telemetry."""
        i = self._index[robot_id]
        pose = Pose2D(float(self.x[i]), float(self.y[i]), float(self.th[i]))
        ranges = self._sonar(i)
        rays = []
        for k, unit in enumerate(self.robot.sonar.units):
            origin = pose.to_world(Vec2(unit.x_m, unit.y_m))
            heading = pose.theta_rad + math.radians(unit.heading_deg)
            reach = float(ranges[k])
            end = origin + Vec2(reach * math.cos(heading), reach * math.sin(heading))
            rays.append((origin, end))
        return rays

    def _event_active(self, kind: str, robot_id: str) -> bool:
        return any(
            e.kind == kind
            and (not e.robots or robot_id in e.robots)
            and e.start_s <= self.t_s + 1e-9 < e.start_s + e.duration_s
            for e in self.events
        )

    def _event_ranges(self, robot_id: str, ranges: FloatArray) -> FloatArray:
        for e in self.events:
            if e.kind == "all_sonars_blocked" and self._event_active(e.kind, robot_id):
                return np.full_like(ranges, e.range_m)
        return ranges

    def sense_all(self) -> FloatArray:
        """Every robot's sonar ranges (robots in the order added, before events), cast in
        one vectorised pass; `status` then reads them. With sonar noise, the draws are
        the same as sensing robot by robot in that order.
        """
        if self._ranges is None:
            self._ranges = self._cast(np.arange(len(self._ids)))
        return self._ranges

    def _sonar(self, i: int) -> FloatArray:
        if self._ranges is not None:
            row: FloatArray = self._ranges[i]
            return row
        if i not in self._sonar_cache:
            self._sonar_cache[i] = self._cast(np.array([i]))[0]
        return self._sonar_cache[i]

    def _cast(self, idx: npt.NDArray[np.intp]) -> FloatArray:
        """Sonar ranges (len(idx), transducers) of robots `idx`, noise drawn in their order."""
        ring = self.ring
        rays = ring_rays(ring, self.x[idx], self.y[idx], self.th[idx])
        owner, cx, cy, r = self._nearby_discs(idx)
        # Only the rays that point towards a disc are tested against it.
        x, y, th = self.x[idx][owner], self.y[idx][owner], self.th[idx][owner]
        bearing = np.arctan2(cy - y, cx - x) - th
        pair, ray = rays_towards(ring, bearing, np.hypot(cx - x, cy - y), r)
        flat = owner[pair] * ring.angle_rad.size + ray
        ox, oy, dx, dy = (a.ravel()[flat] for a in rays)
        nearest = np.full(rays[0].size, np.inf)
        np.minimum.at(nearest, flat, circle_hits_at(ox, oy, dx, dy, cx[pair], cy[pair], r[pair]))
        hits = nearest.reshape(rays[0].shape)
        if self._edges.ax.size:
            hits = np.minimum(hits, self._edge_hits(rays))
        ranges = per_unit(ring, hits)
        if self.noise.sonar_std_m > 0.0:
            ranges = ranges + self.rng.normal(0.0, self.noise.sonar_std_m, ranges.shape)
        return np.asarray(np.clip(ranges, ring.min_range_m, ring.max_range_m), dtype=np.float64)

    def _edge_hits(self, rays: tuple[FloatArray, ...]) -> FloatArray:
        e = self._edges
        ox, oy, dx, dy = (a.ravel() for a in rays)
        out = np.empty(ox.size)
        step = max(1, _CHUNK // e.ax.size)
        for lo in range(0, ox.size, step):
            part = slice(lo, lo + step)
            out[part] = ray_segment_hits(
                ox[part], oy[part], dx[part], dy[part], e.ax, e.ay, e.bx, e.by
            )
        return out.reshape(rays[0].shape)

    def _nearby_discs(
        self, idx: npt.NDArray[np.intp]
    ) -> tuple[npt.NDArray[np.intp], FloatArray, FloatArray, FloatArray]:
        """(row of idx, centre x, y, radius) of every disc the sonar of robots `idx` may
        hear: the obstacle circles within reach, and every other robot
        whose centre is within `reach` (the same test, pair by pair, as always).
        """
        radius = self.robot.radius_m
        reach = self.ring.max_range_m + radius + 0.5
        x, y = self.x[idx], self.y[idx]
        rows, cx, cy, r = [], [], [], []
        if len(self._circles):
            circles = self._circles
            horizon = (
                self.ring.max_range_m
                + self.ring.mount_m
                + _CAST_MARGIN_M
                + _CAST_MARGIN_SIGMAS * self.noise.sonar_std_m
            )
            d = np.hypot(x[:, None] - circles[:, 0], y[:, None] - circles[:, 1])
            ri, k = np.nonzero(d - circles[:, 2] < horizon)
            rows.append(ri)
            cx.append(circles[k, 0])
            cy.append(circles[k, 1])
            r.append(circles[k, 2])
        if idx.size == len(self._ids):
            ri, j = _close_pairs(self.x, self.y, reach)
        else:
            ri, j = np.nonzero(np.ones((idx.size, len(self._ids)), dtype=bool))
            ri, j = ri[j != idx[ri]], j[j != idx[ri]]
        near = np.hypot(self.x[j] - x[ri], self.y[j] - y[ri]) < reach
        rows.append(ri[near])
        cx.append(self.x[j[near]])
        cy.append(self.y[j[near]])
        r.append(np.full(int(near.sum()), radius))
        cat = np.concatenate
        return cat(rows), cat(cx), cat(cy), cat(r)
