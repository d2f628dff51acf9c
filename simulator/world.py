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
from collections import deque
from collections.abc import Mapping, Sequence
from typing import Generic, TypeVar

import numpy as np
import numpy.typing as npt

from phalanx.core.config import NoiseConfig, Scenario, SensorEvent, WorldConfig
from phalanx.core.fixes import PoseFix, RelativeFix
from phalanx.core.geometry import Pose2D, Twist2D, Vec2
from phalanx.core.localisation import LocalisationConfig
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.core.robot_params import RobotParams
from phalanx.core.scenarios import resolve_world
from phalanx.simulator.contacts import Contacts, polygon_edges
from phalanx.simulator.kinematics import (
    SCALAR_MAX,
    apply_robot_limits,
    integrate_arcs,
    limits_and_arcs_scalar,
)
from phalanx.simulator.scene import SonarScene
from phalanx.simulator.sensors import SimulatedSensors, camera_mounts
from phalanx.simulator.sonar import SonarRing

FloatArray = npt.NDArray[np.float64]
T = TypeVar("T")


class Delay(Generic[T]):
    """A value `ticks` steps late: `push` one each step, get back the one pushed `ticks`
    steps before; before there was one, `initial` (None: the first value pushed).
    """

    def __init__(self, ticks: int, initial: T | None = None) -> None:
        self._values: deque[T] = deque(maxlen=ticks + 1)
        if initial is not None:
            self._values.extend([initial] * ticks)

    def push(self, value: T) -> T:
        """Take this step's value; the one of `ticks` steps ago."""
        if not self._values:
            self._values.extend([value] * (self._values.maxlen or 1))
        self._values.append(value)
        return self._values[0]


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
        self._ids: list[str] = []
        self._index: dict[str, int] = {}
        z = np.zeros(0)
        self.x, self.y, self.th, self.v, self.w = z, z.copy(), z.copy(), z.copy(), z.copy()
        self.v_cmd, self.w_cmd = z.copy(), z.copy()
        self.odo = np.zeros((0, 3))
        self.bumped = np.zeros(0, dtype=bool)
        self._circles = np.array([(c.x_m, c.y_m, c.radius_m) for c in world.circles]).reshape(-1, 3)
        self._edges = polygon_edges(world)
        self.contacts = Contacts(world, self._circles, self._edges, self._ids)
        self.scene = SonarScene(
            self.ring, self._circles, self._edges, robot_radius_m=robot.radius_m,
            sonar_std_m=noise.sonar_std_m, rng=self.rng,
        )  # fmt: skip
        self.collisions = self.contacts.collisions  # every contact as it began
        self._sonar_cache: dict[int, FloatArray] = {}
        self._ranges: FloatArray | None = None  # every robot's, when cast in one pass
        self.sensors: SimulatedSensors | None = None  # positioning sensors, if simulated
        # (a firmware's lateness, in control periods of `world.command_delay_s` & co.)
        self._commands: Delay[dict[str, Twist2D]] | None = None
        self._readings: Delay[FloatArray] | None = None
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
        late = (world.config.command_delay_s, world.config.sonar_delay_s)
        commands, readings = (round(delay_s / scenario.dt_s) for delay_s in late)
        world._commands = Delay(commands, initial={}) if commands else None
        world._readings = Delay(readings) if readings else None
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

    def place(self, robot_id: str, pose: Pose2D, twist: Twist2D) -> None:
        """Put a robot that moves on its own (a real robot, or one another simulator
        moves) where it was observed, moving as it was: the world carries it along its
        twist until it is placed again, so the other robots sense it and contacts count.
        """
        i = self._index[robot_id]
        self.x[i], self.y[i], self.th[i] = pose.x_m, pose.y_m, pose.theta_rad
        self.v[i] = self.v_cmd[i] = twist.v_mps
        self.w[i] = self.w_cmd[i] = twist.omega_radps
        self.odo[i] = (pose.x_m, pose.y_m, pose.theta_rad)
        self._sonar_cache.clear()
        self._ranges = None

    # --- motion ------------------------------------------------------------------------

    def step(self, commands: Mapping[str, Twist2D], dt_s: float) -> None:
        """Advance `dt_s`: robots chase their commands within limits, in sub-steps (the
        commands of `world.command_delay_s` ago, when the robots' firmware is late).
        """
        if self._commands is not None:
            commands = self._commands.push(dict(commands))
        for rid, cmd in commands.items():
            i = self._index[rid]
            self.v_cmd[i], self.w_cmd[i] = cmd.v_mps, cmd.omega_radps
        sub = dt_s / self.config.substeps
        self.bumped[:] = False
        if self.sensors is None and self._contact_free(dt_s):
            self._glide(sub)
            self._update_odometry(dt_s)
            self.t_s += dt_s
            self._sonar_cache.clear()
            self._ranges = None
            return
        # (only the robots near a polygon can touch one in this step's sub-steps)
        walls = self.contacts.near_walls(self.x, self.y, self.robot.radius_m, self._travel_m(dt_s))
        start = self._poses() if self.sensors is not None else None
        for j in range(self.config.substeps):
            before = self._poses() if self.sensors is not None else None
            self._substep(sub, walls)
            if self.sensors is not None and before is not None:
                self.sensors.substep(self.t_s + j * sub, sub, before, self._poses())
        if self.sensors is not None and self.sensors.odometry is not None and start is not None:
            self.odo = self.sensors.odometry_step(start, self._poses())
        else:
            self._update_odometry(dt_s)
        self.t_s += dt_s
        self._sonar_cache.clear()
        self._ranges = None

    def _travel_m(self, dt_s: float) -> float:
        """How far any robot can move within the next `dt_s`: no further than its speed
        allows (no faster than it goes or may go, `_towards` never overshoots its target).
        """
        fastest = max(max(map(abs, self.v.tolist()), default=0.0), self.robot.v_max_mps)
        return fastest * dt_s * (1.0 + 1e-6)

    def _contact_free(self, dt_s: float) -> bool:
        """Whether no contact can begin or end within the next `dt_s` (the usual case)."""
        travel_m = self._travel_m(dt_s)
        return self.contacts.none_within(self.x, self.y, self.robot.radius_m, travel_m)

    def _glide(self, dt_s: float) -> None:
        """Every sub-step of `dt_s` with no contact checks (`_contact_free` holds): the
        same arithmetic as `_substep`'s when nothing touches.
        """
        n = self.config.substeps
        if len(self._ids) <= SCALAR_MAX:
            state = (self.x, self.y, self.th, self.v, self.w, self.v_cmd, self.w_cmd)
            self.v, self.w, self.x, self.y, self.th = limits_and_arcs_scalar(
                state, self.robot, dt_s, substeps=n
            )
            return
        for _ in range(n):
            self.v, self.w = apply_robot_limits(
                self.v, self.w, self.v_cmd, self.w_cmd, self.robot, dt_s
            )
            self.x, self.y, self.th = integrate_arcs(self.x, self.y, self.th, self.v, self.w, dt_s)

    def _substep(self, dt_s: float, walls: list[int] | None = None) -> None:
        """One sub-step with its contact checks (the polygons' for robots `walls` only,
        None: every robot).
        """
        if len(self._ids) <= SCALAR_MAX:
            self.v, self.w, x, y, th = limits_and_arcs_scalar(
                (self.x, self.y, self.th, self.v, self.w, self.v_cmd, self.w_cmd), self.robot, dt_s
            )
        else:
            self.v, self.w = apply_robot_limits(
                self.v, self.w, self.v_cmd, self.w_cmd, self.robot, dt_s
            )
            x, y, th = integrate_arcs(self.x, self.y, self.th, self.v, self.w, dt_s)
        radius_m = self.robot.radius_m
        touching = self.contacts.touching(x, y, radius_m, walls)
        if not touching:  # the usual case: every robot moves
            self.x, self.y, self.th = x, y, th
        else:
            blocked = np.zeros(len(self._ids), dtype=bool)
            for i, other in touching:
                blocked[i] = True
                self.contacts.record(i, other, self.t_s)
            keep = ~blocked
            self.x, self.y, self.th = (
                np.where(keep, x, self.x),
                np.where(keep, y, self.y),
                np.where(keep, th, self.th),
            )
            self.v, self.w = np.where(keep, self.v, 0.0), np.where(keep, self.w, 0.0)
            self.bumped |= blocked
        self.contacts.settle(touching, self.x, self.y, radius_m)

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
        # (the events' windows checked once for all robots: most ticks have none open)
        events = any(e.start_s <= self.t_s + 1e-9 < e.start_s + e.duration_s for e in self.events)
        if events:
            ranges = np.array(
                [self._event_ranges(rid, row) for rid, row in zip(self._ids, ranges, strict=True)]
            )
        bumped = self.bumped.tolist()
        out = []
        for i, (rid, row) in enumerate(zip(self._ids, ranges.tolist(), strict=True)):
            bumper = bumped[i] or (events and self._event_active("bumper", rid))
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
            ranges = self.scene.cast(self.x, self.y, self.th, np.arange(len(self._ids)))
            if self._readings is not None:  # the firmware's reading of a while ago
                ranges = self._readings.push(ranges)
            self._ranges = ranges
        return self._ranges

    def _sonar(self, i: int) -> FloatArray:
        if self._ranges is not None or self._readings is not None:
            # (a late firmware's readings come from the ring cast for all every step)
            row: FloatArray = self.sense_all()[i]
            return row
        if i not in self._sonar_cache:
            self._sonar_cache[i] = self.scene.cast(self.x, self.y, self.th, np.array([i]))[0]
        return self._sonar_cache[i]
