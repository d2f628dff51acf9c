"""The sense stage of a step: what the sonar ring and bumpers say, for this robot and
the group's rules. Echoes of the formation's own robots are masked out; the reading
feeds the leader's map; the path each way is blocked or not; the way ahead is clear
enough to lead; an obstacle is inside the braking distance.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from phalanx.agents.inputs import FleetView, Observation
from phalanx.agents.masking import (
    EXPECTED_MASK_M,
    TRACKED_MASK_M,
    FixedDiscs,
    MaskInputs,
    SlotMasks,
    mask_readings,
    unmasked,
)
from phalanx.agents.memory import Progress, Route
from phalanx.agents.navigation import (
    Breadcrumbs,
    NavSettings,
    RoutePlanner,
    StallWatch,
    bearing_rad,
    clearance_along,
)
from phalanx.agents.perception import MaskedEchoes, SonarEchoes, SonarGeometry, braking_gap_m
from phalanx.agents.shape import Points, Shape
from phalanx.core.frozen import quick_init
from phalanx.core.geometry import Pose2D, Twist2D, Vec2
from phalanx.core.limits import KinematicLimits
from phalanx.core.robot import Odometry
from phalanx.core.states import State

STANDSTILL_MPS = 0.01
__all__ = ["EXPECTED_MASK_M", "STANDSTILL_MPS", "TRACKED_MASK_M", "Senses", "Sensing", "Stance"]
# The emergency stop's corridor hugs the body: a wall passed alongside must not stop it.
ESTOP_MARGIN_M = 0.02
# A route leading further round than this from the heading goes back the way it came.
BEHIND_RAD = math.radians(100.0)
# ... and only one that has led back this long (s; two re-plans running) is a dead end:
# sonar arcs come and go on the map, and a route turned back by one of them for a single
# re-plan (the mouth of a passage closed by an arc, then open again) is none.
DEAD_END_CONFIRM_S = 2.0
# ... and leads back the way it came: the point it heads for within this of the path the
# robot drove (m), but for the last of it (m, the ground it stands on). One turning back
# round the end of a wall it drove along leads elsewhere: the group drives on round it.
CAME_BY_M = 1.0
CAME_BY_SKIP_M = 2.0
# A robot whose route turns off by more than this cannot lead on from where it is.
REORIENT_ROUTE_RAD = math.radians(60.0)
# A command never drives the body nearer than this to an echo (`ContactGuard`).
CONTACT_MARGIN_M = 0.01
# An emergency stop ends with this much room beyond the braking distance, not less.
RELEASE_MARGIN_M = 0.1
# A follower this close along its heading to its slot goes the way the slot goes.
INTENT_M = 0.05
_NAVIGATING = (State.NAVIGATE, State.WANDER)


@quick_init
@dataclass(frozen=True, slots=True)
class Sensing:
    """A step's reading of the sonar ring and bumpers (body frame, m)."""

    points: Points  # known robots removed
    raw: Points  # every echo
    ahead_m: float  # own free way straight ahead
    blocked: dict[int, bool]  # path blocked, forwards (+1) and backwards (-1)
    path_clear: bool
    imminent: bool
    bumper: bool
    dead_end: bool = False


@quick_init
@dataclass(frozen=True, slots=True)
class Stance:
    """Where this robot stands before the step decides: its behaviour state and its
    direction of motion (both as the last step left them), its last command.
    """

    state: str
    direction: int
    last_command: Twist2D


class Senses:
    """Turns one robot's readings into a `Sensing` (and keeps its map and stall watch)."""

    def __init__(
        self,
        robot_id: str,
        settings: NavSettings,
        *,
        sonar: SonarGeometry,
        shape: Shape,
        limits: KinematicLimits,
        planner: RoutePlanner,
        progress: Progress,
        route: Route,
        crumbs: Breadcrumbs,
        fold: Callable[[], bool] = lambda: False,
    ) -> None:
        self.robot_id = robot_id
        self.nav = settings.nav
        self.near_m = settings.deadlock.obstacle_range_m
        # (a follower in reactive navigation leaves its slot for what is this near)
        self.follower_near_m = self.nav.avoid_range_m if self.nav.reactive else self.near_m
        self.dt_s = settings.dt_s
        self.sonar, self.shape, self.limits = sonar, shape, limits
        self.planner, self.progress, self.plan = planner, progress, settings.plan
        self.route = route
        self.stall = StallWatch(self.nav.stall_s)
        self._boxed_since_s: float | None = None  # since when the route has led back
        self._quiet: tuple[tuple[float, ...], SonarEchoes] | None = None  # (`_read`)
        # Asked before a dead end is declared: fold the group into a narrower shape
        # if it has one (True: a fold is coming, the way may open for it).
        self.fold = fold
        self.crumbs = crumbs  # the path the robot drove (what it backs along)
        # (the scenario's shape: only the slots within hearing, not every robot's)
        self.remask((shape.slots_within(self._audible_m()),))

    def _audible_m(self) -> float:
        """How far from this robot's slot another's may be for its sonar to hear it."""
        sonar, shape = self.sonar, self.shape
        return sonar.mount_m + sonar.max_range_m + shape.radius_m + EXPECTED_MASK_M + 1.0

    def remask(self, shapes: tuple[dict[str, Vec2], ...]) -> None:
        """Where the formation's robots are expected (every slot they have in `shapes`,
        offsets from this robot's slot): the robots near enough for the sonar to hear
        are masked, with where their echoes would come from worked out once (the shape
        is rigid between two changes).
        """
        shape, sonar, audible_m = self.shape, self.sonar, self._audible_m()
        slots = [
            (r, p)
            for offsets in shapes
            for r, p in offsets.items()
            if r != self.robot_id and p.norm() < audible_m
        ]
        # A robot behind another in a column is not clear to lead, whatever its sonar
        # sees past the one ahead (masked out of it).
        self.robot_ahead = any(
            0.0 < p.x_m < self.nav.clear_range_m + shape.radius_m
            and abs(p.y_m) < shape.half_width_m + shape.radius_m
            for _, p in slots
        )
        discs = FixedDiscs.of(sonar, [p for _, p in slots], shape.radius_m + EXPECTED_MASK_M)
        self.slot_masks = SlotMasks.of(
            [r for r, _ in slots], discs, tracked_radius_m=shape.radius_m,
            half_width_m=shape.half_width_m,
        )  # fmt: skip

    def read(
        self,
        observation: Observation,
        view: FleetView,
        stance: Stance,
        *,
        t_s: float,
        assume_formed: bool,
    ) -> Sensing:
        """The step's sensing. `assume_formed`: robots not heard yet count as in their
        slots (the scenario's start).
        """
        odometry, status = observation.odometry, observation.status
        pose = odometry.pose
        # (the batch runner reads and masks every robot's ring in one pass; alone, here)
        reading = observation.sonar or self._read(status.sonar_ranges_m)
        mask = observation.masked
        if mask is None or mask.robot_id != self.robot_id or mask.t_s != t_s:
            mask = self._mask(reading, view, stance.state, pose, assume_formed, t_s)
        raw, masked, ahead_m, behind_m = reading.raw, mask.points, mask.ahead_m, mask.behind_m
        if self.plan != "scripted" and self.nav.reactive:
            self.planner.add(observation.scans)
            self.planner.see(pose, self.sonar, reading.ranges_m, mask.echo, t_s)
        bumper = any(status.bumpers)
        dead_end = self._dead_end(pose, masked, stance.state, t_s)
        # (short-circuit kept: the stall watch runs only with room ahead, or a fold coming)
        near_m = self.near_m if view.is_leader else self._follower_near_m(stance.state)
        blocked_ahead = (
            (ahead_m < near_m and not self._folds_instead(view.is_leader, stance.state))
            or self._stalled(pose, t_s, stance.state)
            or dead_end
        )
        return Sensing(
            points=masked,
            raw=raw,
            ahead_m=ahead_m,
            blocked={1: blocked_ahead or bumper, -1: behind_m < self.near_m or bumper},
            path_clear=stance.direction > 0
            and ahead_m >= self.nav.clear_range_m
            and not self.robot_ahead
            and self._route_ahead(pose, view, t_s),
            imminent=self.nav.reactive
            and (bumper or self._imminent(raw, reading.nearest_m, odometry, stance.last_command)),
            bumper=bumper,
            dead_end=dead_end,
        )

    def _read(self, ranges_m: tuple[float, ...]) -> SonarEchoes:
        """`SonarGeometry.read` of the ranges; a reading without an echo (open space) is
        kept, and the same ranges next time are the same reading.
        """
        quiet = self._quiet
        if type(ranges_m) is not tuple:  # (a tuple's values cannot change behind it)
            return self.sonar.read(ranges_m)
        if quiet is not None and quiet[0] == ranges_m:
            return quiet[1]
        reading = self.sonar.read(ranges_m)
        if not np.count_nonzero(reading.echo):
            self._quiet = (ranges_m, reading)
        return reading

    def _mask(
        self,
        reading: SonarEchoes,
        view: FleetView,
        state: str,
        pose: Pose2D,
        assume_formed: bool,
        t_s: float,
    ) -> MaskedEchoes:
        """The reading with the formation's robots masked out (`mask_readings`); the one
        `_read` kept, without an echo, has nothing to mask.
        """
        if self._quiet is not None and reading is self._quiet[1]:
            return unmasked(reading, self.robot_id, t_s)
        inputs = MaskInputs(self.robot_id, view, state, pose, assume_formed, t_s)
        return mask_readings(self.sonar, [reading], [inputs], self.slot_masks)[0]

    def _follower_near_m(self, state: str) -> float:
        """How near ahead an obstacle blocks this robot as a follower: `avoid_range_m`,
        or, stopped for one, anything that leaves it no room to start again (the stop's
        release gap): it then goes round instead of standing there.
        """
        if state != State.EMERGENCY_STOP:
            return self.follower_near_m
        return max(self.follower_near_m, release_gap_m(self.shape))

    def _folds_instead(self, is_leader: bool, state: str) -> bool:
        """A navigating leader whose own way ahead is blocked folds the group into its
        narrowest shape first, if it is not folded yet (True: a fold is coming), as a
        stalled one does: the narrower shape may find a way the wider could not. It is
        blocked only once folded.
        """
        return is_leader and state in _NAVIGATING and self.fold()

    def _stalled(self, pose: Pose2D, t_s: float, state: str) -> bool:
        """A navigating leader that turns and creeps without getting anywhere is blocked
        as surely as one facing a wall: say so, and the group's rules take over; but a
        group that can fold into a narrower shape folds first (the leader, turning on
        the spot from one way the whole shape might take to another, finds one the
        narrower shape can).
        """
        if state not in _NAVIGATING or self.plan == "scripted":
            self.stall.reset()
            return False
        return self.stall.stalled(pose, t_s) and not self.fold()

    def _route_ahead(self, pose: Pose2D, view: FleetView, t_s: float) -> bool:
        """Whether the way to the goal goes on ahead of this robot (so it could lead):
        a follower asks its map only while the leader is blocked and might hand over.
        """
        waypoints, waypoint = self.route.waypoints, self.progress.waypoint
        if self.plan != "goto" or self.planner.map is None or waypoint >= len(waypoints):
            return True
        if not view.is_leader:
            head = view.live.get(view.leader_id)
            if head is None or not head.obstacle:
                return True
            carrot = self.planner.towards(pose, Vec2(*waypoints[waypoint]), t_s)
        else:
            carrot = self.planner.carrot or Vec2(*waypoints[waypoint])
        return abs(bearing_rad(pose, carrot)) <= REORIENT_ROUTE_RAD

    def _dead_end(self, pose: Pose2D, points: Points, state: str, t_s: float) -> bool:
        """`_boxed_in` for `DEAD_END_CONFIRM_S` running."""
        if not self._boxed_in(pose, points, state):
            self._boxed_since_s = None
            return False
        if self._boxed_since_s is None:
            self._boxed_since_s = t_s
        return t_s - self._boxed_since_s >= DEAD_END_CONFIRM_S - 1e-9

    def _boxed_in(self, pose: Pose2D, points: Points, state: str) -> bool:
        """A navigating leader whose route leads back the way it came, with no room for
        the shape to turn round where it is, and no narrower shape to fold into first
        (whose route may go on): the dead end the deadlock reverse is for.
        """
        carrot = self.planner.carrot
        if state not in _NAVIGATING or carrot is None:
            return False
        leads_back = abs(bearing_rad(pose, carrot)) > BEHIND_RAD and self._came_by(carrot)
        return leads_back and not self.shape.sweep_clear(points, rigid=True) and not self.fold()

    def _came_by(self, point: Vec2) -> bool:
        """Whether `point` lies on the way this robot came (`CAME_BY_M` of its path, but
        for the last `CAME_BY_SKIP_M`); with less of its path known than that (a new
        leader), any point behind it does.
        """
        came = self.crumbs.came_by(point, within_m=CAME_BY_M, skip_m=CAME_BY_SKIP_M)
        return came is None or came

    def _imminent(self, raw: Points, nearest: float, odometry: Odometry, last: Twist2D) -> bool:
        """An obstacle (any, robots included) inside the braking distance + margin."""
        v_mps = odometry.twist.v_mps
        moving = v_mps if abs(v_mps) > STANDSTILL_MPS else last.v_mps
        if abs(moving) <= STANDSTILL_MPS:
            return False  # turning on the spot: a round robot sweeps nothing new
        speed = max(abs(v_mps), abs(last.v_mps))
        braking = braking_gap_m(speed, decel_mps2=self.limits.decel_mps2, latency_s=2 * self.dt_s)
        half_width = self.shape.radius_m + ESTOP_MARGIN_M
        if nearest > braking + self.nav.stop_margin_m + half_width:
            return False  # nothing near enough to matter, whatever the heading
        way = 0.0 if moving > 0 else math.pi
        gap = clearance_along(raw, way, half_width_m=half_width)
        return gap < braking + self.nav.stop_margin_m


def way_clear(sensing: Sensing, shape: Shape, view: FleetView, pose: Pose2D) -> bool:
    """Room to brake from cruise speed the way this robot means to go (what ends an
    emergency stop): forwards for a leader; for a follower, the way to its slot (or,
    on it, the way its slot moves).
    """
    backwards = False
    if view.slot is not None and not view.is_leader:
        target, ff = view.slot
        offset = target.position - pose.position
        along = offset.x_m * math.cos(pose.theta_rad) + offset.y_m * math.sin(pose.theta_rad)
        backwards = along < -INTENT_M or (abs(along) <= INTENT_M and ff.v_mps < 0.0)
    return clear_towards(sensing, shape, backwards=backwards)


def clear_towards(sensing: Sensing, shape: Shape, *, backwards: bool) -> bool:
    """Room to brake from cruise speed (`release_gap_m`) straight ahead, or straight
    behind.
    """
    gap = clearance_along(
        sensing.raw, math.pi if backwards else 0.0, half_width_m=shape.radius_m + ESTOP_MARGIN_M
    )
    return gap >= release_gap_m(shape)


def release_gap_m(shape: Shape) -> float:
    """The free way ahead an emergency stop ends with: room to brake from cruise speed,
    and `RELEASE_MARGIN_M` more (m).
    """
    return shape.stop_gap_m() + RELEASE_MARGIN_M


@dataclass(frozen=True, slots=True)
class ContactGuard:
    """No command drives the robot, in the step it asks for (at most `v_max_mps`, what
    the limiter lets through), within `CONTACT_MARGIN_M` of an echo ahead of it the way
    it drives; turning, and driving away, are left alone. `on`: a reactive scenario.

    The emergency stop watches a robot that moves (its speed, or its last command): a
    robot standing against an obstacle whose behaviour then drives it that way (a
    follower in reverse whose slot is ahead, past the obstacle) would take one step
    into it before the stop, and a step more at every retry.
    """

    radius_m: float
    dt_s: float
    v_max_mps: float
    on: bool = True

    def apply(self, command: Twist2D, sensing: Sensing) -> Twist2D:
        """`command`, its speed cut to 0 where it would bring the body that near."""
        v_mps = command.v_mps
        if v_mps == 0.0 or not self.on:
            return command
        x, y = sensing.raw
        ahead = x > 0.0 if v_mps > 0.0 else x < 0.0
        way = 0.0 if v_mps > 0.0 else math.pi
        gap_m = clearance_along((x[ahead], y[ahead]), way, half_width_m=self.radius_m)
        if gap_m >= min(abs(v_mps), self.v_max_mps) * self.dt_s + CONTACT_MARGIN_M:
            return command
        return Twist2D(0.0, command.omega_radps)
