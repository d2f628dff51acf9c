"""The simulated world: ground truth of every robot, obstacles, sonar, collisions,
odometry (with optional seeded noise) and scripted sensor events.

Robot state lives in numpy arrays (one entry per robot) so a step of 1000 robots is a
handful of vector operations; sonar is ray-cast lazily, per robot, against only the
obstacles and robots within sonar range.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from phalanx.core.config import NoiseConfig, RobotParams, Scenario, SensorEvent, WorldConfig
from phalanx.core.fixes import PoseFix, RelativeFix
from phalanx.core.geometry import Pose2D, Twist2D, Vec2
from phalanx.core.localisation import LocalisationConfig
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.core.runlog import Collision
from phalanx.core.scenarios import resolve_world
from phalanx.simulator.kinematics import apply_robot_limits, integrate_arcs
from phalanx.simulator.sensors import SimulatedSensors, camera_mounts
from phalanx.simulator.sonar import SonarRing, ray_circle_hits, ray_segment_hits

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


# Up to this many robots, a pairwise distance check first rules out any contact at once.
_PAIRWISE_MAX = 64


def _any_pair_within(x: FloatArray, y: FloatArray, distance_m: float) -> bool:
    """Whether any two of the points (x, y) lie closer than `distance_m`."""
    if len(x) < 2:
        return False
    d2 = (x[:, None] - x[None, :]) ** 2 + (y[:, None] - y[None, :]) ** 2
    np.fill_diagonal(d2, np.inf)
    # a hair wide of the grid's exact hypot test: never misses a contact it would find
    return bool(d2.min() < (distance_m * (1.0 + 1e-9)) ** 2)


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
        localisation: LocalisationConfig | None = None,
        mounts_rad: Mapping[str, float] | None = None,
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
        self.sensors: SimulatedSensors | None = None  # positioning sensors, if simulated
        if localisation is not None:
            self._attach_sensors(localisation, dict(mounts_rad or {}), seed)

    def _attach_sensors(
        self, config: LocalisationConfig, mounts_rad: dict[str, float], seed: int
    ) -> None:
        e = self._edges
        sensors = SimulatedSensors(
            config,
            track_m=self.robot.track_width_m,
            robot_radius_m=self.robot.radius_m,
            seed=seed,
            obstacles=(self._circles, (e.ax, e.ay, e.bx, e.by)),
            mounts_rad=mounts_rad,
            events=self.events,
        )
        self.sensors = sensors if sensors.active else None

    @classmethod
    def for_scenario(cls, scenario: Scenario, robot: RobotParams) -> World:
        """The scenario's world with every robot at its start pose."""
        world = cls(
            robot=robot,
            world=scenario.world,
            noise=scenario.noise,
            events=scenario.events,
            seed=scenario.seed,
            localisation=scenario.localisation,
            mounts_rad=camera_mounts(scenario),
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
        if self.sensors is not None:
            self.sensors.add_robot(robot_id, pose.x_m, pose.y_m, pose.theta_rad)

    # --- motion ------------------------------------------------------------------------

    def step(self, commands: Mapping[str, Twist2D], dt_s: float) -> None:
        """Advance `dt_s`: robots chase their commands within limits, in sub-steps."""
        for rid, cmd in commands.items():
            i = self._index[rid]
            self.v_cmd[i], self.w_cmd[i] = cmd.v_mps, cmd.omega_radps
        sub = dt_s / self.config.substeps
        self.bumped[:] = False
        start = self._poses() if self.sensors is not None else None
        for j in range(self.config.substeps):
            before = self._poses() if self.sensors is not None else None
            self._substep(sub)
            if self.sensors is not None and before is not None:
                self.sensors.substep(self.t_s + j * sub, sub, before, self._poses())
        if self.sensors is not None and self.sensors.odometry is not None and start is not None:
            self.odo = self.sensors.odometry_step(start, self._poses())
        else:
            self._update_odometry(dt_s)
        self.t_s += dt_s
        self._sonar_cache.clear()

    def _substep(self, dt_s: float) -> None:
        self.v, self.w = apply_robot_limits(
            self.v, self.w, self.v_cmd, self.w_cmd, self.robot, dt_s
        )
        x, y, th = integrate_arcs(self.x, self.y, self.th, self.v, self.w, dt_s)
        touching = self._touching(x, y, self.robot.radius_m)
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
        if len(x) <= _PAIRWISE_MAX and not _any_pair_within(x, y, 2 * radius):
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

    def _poses(self) -> FloatArray:
        return np.column_stack([self.x, self.y, self.th])

    # --- sensing -----------------------------------------------------------------------

    def positioning(self, robot_id: str) -> tuple[tuple[PoseFix, ...], tuple[RelativeFix, ...]]:
        """The pose fixes and relative measurements that have reached `robot_id` since it
        last asked (none without simulated positioning sensors).
        """
        if self.sensors is None:
            return (), ()
        return self.sensors.take(self._index[robot_id], self.t_s)

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

    def _sonar(self, i: int) -> FloatArray:
        if i not in self._sonar_cache:
            self._sonar_cache[i] = self._cast(i)
        return self._sonar_cache[i]

    def _cast(self, i: int) -> FloatArray:
        ring = self.ring
        c, s = math.cos(self.th[i]), math.sin(self.th[i])
        ox = self.x[i] + c * ring.origin_x - s * ring.origin_y
        oy = self.y[i] + s * ring.origin_x + c * ring.origin_y
        ang = self.th[i] + ring.angle_rad
        dx, dy = np.cos(ang), np.sin(ang)
        cx, cy, r = self._nearby_circles(i)
        hits = ray_circle_hits(ox, oy, dx, dy, cx, cy, r)
        e = self._edges
        hits = np.minimum(hits, ray_segment_hits(ox, oy, dx, dy, e.ax, e.ay, e.bx, e.by))
        per_unit = np.full(ring.units, np.inf)
        np.minimum.at(per_unit, ring.unit_of_ray, hits)
        if self.noise.sonar_std_m > 0.0:
            per_unit = per_unit + self.rng.normal(0.0, self.noise.sonar_std_m, ring.units)
        return np.asarray(np.clip(per_unit, ring.min_range_m, ring.max_range_m), dtype=np.float64)

    def _nearby_circles(self, i: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Obstacle circles and other robots' discs within sonar reach of robot i."""
        reach = self.ring.max_range_m + self.robot.radius_m + 0.5
        near = np.hypot(self.x - self.x[i], self.y - self.y[i]) < reach
        near[i] = False
        cx = np.concatenate([self._circles[:, 0], self.x[near]])
        cy = np.concatenate([self._circles[:, 1], self.y[near]])
        r = np.concatenate([self._circles[:, 2], np.full(int(near.sum()), self.robot.radius_m)])
        return cx, cy, r
