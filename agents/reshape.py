"""Changing the formation's shape when the way demands it (formation reconfiguration):
the leader plans its route for the shape's footprint over the fleet's map and, when
the scenario's shape only gets through by a long way round (or not at all) while a
narrower one passes, it folds the group on the move (`RESHAPE`): separations across
the heading shrunk, or every robot into a column behind it. Once the wider shape fits
where the group is and its route is as good, it unfolds again; the shape the
scenario asks for is the one it goes back to.

The transition is planned (`phalanx.core.shapes`): each robot's slot slides on a
straight line in the formation frame to its new one, all at the same fraction of the way
(CAPT: no robot crosses another's path), while the leader drives on along its route:
while the group narrows, as fast as every follower can keep to its sliding slot (into a
column they drop back, and the leader drives on as navigation would), slowly while it
widens (they come up beside it); the followers' slots slide under them as they go, and
where the way ahead does not fit the shape as it is at that moment, the leader's steering
stops it. The shape in effect (`ShapeKey`) goes out in the leader's flags; followers take
it from there, so every robot computes the same slots.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Protocol

import numpy as np

from phalanx.agents.behaviours.base import Behaviour, Moment
from phalanx.agents.leadership import FlagsView
from phalanx.agents.navigation import OccupancyMap
from phalanx.agents.shape import Shape
from phalanx.core.geometry import ZERO_TWIST, Pose2D, Twist2D, Vec2
from phalanx.core.shapes import RAMP_SHARE, SCENARIO_SHAPE, ShapeBook, ShapeKey

# Slots slide at up to this speed (m/s) in the formation frame during a reshape, at this
# speed on average (the speed rises and falls over the ends of the slide, `slide_share`),
# and it takes at least this long; the followers then have this long to settle in the new
# shape. Meanwhile the leader drives on no faster than `RESHAPE_CRUISE_MPS` while the
# slots widen (slide and drive together within about a P3DX's 0.3 m/s: a follower that
# falls behind its slot at the fastest of a slide catches up as it slows); while they
# narrow, as fast as keeps every follower's slot within the speed limit
# (`ShapeKeeper.drive_cap_mps`).
RESHAPE_PEAK_MPS = 0.255
RESHAPE_MPS = RESHAPE_PEAK_MPS * (1 - RAMP_SHARE)
RESHAPE_MIN_S = 3.0
SETTLE_S = 2.0
RESHAPE_CRUISE_MPS = 0.1
# A footprint keeps this much more than the shape's half-span off obstacles (m).
FOOTPRINT_MARGIN_M = 0.15
# A shape's route is as good as the best when it is no longer than DETOUR_SHARE times
# the shortest of any shape's, plus DETOUR_M (m).
DETOUR_SHARE = 1.25
DETOUR_M = 2.0
# How often the leader weighs the shapes (s), how many times running a change must be
# wanted, and how long after a reshape before the next.
DECIDE_S = 1.0
CONFIRM = 2
DWELL_S = 5.0
# The sonar showing the way too narrow for the shape this long folds the group, if its
# fold is long: one whose leader drives on at least this far while the slots slide back
# (`slide_drive_m`, m).
# A group that folds in less rides on in its shape, round what the steering can go
# round, and folds where its leader stalls or is blocked.
SQUEEZE_S = 1.0
SQUEEZE_FROM_M = 1.0
# A wider shape is taken only where it fits with the leader here and this far on (m);
# the scenario's shape also where the map shows the way as wide as it as far as the
# leader drives while the slots slide back, and this much further (m).
UNFOLD_AHEAD_M = (0.0, 1.0, 2.0)
UNFOLD_BEYOND_M = 1.0
# The scenario's shape fits the way where the way is as wide as its slots across, with
# the leader where it is and this far along its route (m): room to stay whole, or to
# change shape before; the row of slots shifted to a side by one of these if need be (m).
FITS_ALONG_M = (1.0, 2.0)
FITS_SHIFTS_M = (0.0, -0.25, 0.25, -0.5, 0.5)
# A route's heading at one of its points: from the point this many before to as many after.
ROUTE_HEADING_SPAN = 2


@dataclass
class ShapeKeeper:
    """The shape in effect (the leader's to change, the followers' to copy), and the
    leader's choice of the next one.
    """

    book: ShapeBook
    radius_m: float
    enabled: bool = True
    key: ShapeKey = field(default_factory=ShapeKey)
    wanted: int = SCENARIO_SHAPE
    _candidate: int = SCENARIO_SHAPE
    _count: int = 0
    _decided_s: float = -math.inf
    _gauged_s: float = -math.inf
    _settled_s: float = -math.inf
    squeezed_s: float = 0.0  # how long the sonar has shown the way too narrow for the shape
    # Whether the scenario's shape fits the way, as the map showed it when the leader last
    # weighed the shapes or gauged the way (`gauge`): its footprint's route to the goal is
    # about as good as the best, and the way is as wide as the shape where the group is
    # and along the route (`fits_along`).
    scenario_fits: bool = True

    @cached_property
    def slide_drive_m(self) -> float:
        """How far the leader drives on while the slots slide back from the narrowest
        shape into the scenario's (m): `RESHAPE_CRUISE_MPS` for as long as the longest
        slide takes. A group's fold is long when this is (a fold slides as long, driven
        faster: `drive_cap_mps`).
        """
        return RESHAPE_CRUISE_MPS * slide_s(self.book, SCENARIO_SHAPE, self.book.distinct[-1])

    def copy_from(self, leader: FlagsView) -> None:
        """Take the leader's shape as it published it."""
        self.key = ShapeKey(leader.shape_source, leader.shape_target, leader.morph)

    def footprint_m(self, shape: int) -> float:
        """How far a route for `shape` keeps off obstacles (m)."""
        return self.book.half_span_m(shape, self.radius_m) + FOOTPRINT_MARGIN_M

    @property
    def reshape_wanted(self) -> bool:
        """The leader wants another shape than the one it is in (or is between two)."""
        return self.enabled and (self.wanted != self.key.target or not self.key.settled)

    def drive_cap_mps(self, v_max_mps: float) -> float:
        """How fast the leader may drive on while the slots slide (m/s). While they slide
        into a narrower shape, as fast as keeps every follower's slot within `v_max_mps`
        over the ground at the slide's fastest (driving straight; into a column the
        followers drop back, and that is about `v_max_mps`), and no slower than
        `RESHAPE_CRUISE_MPS`; while they widen, `RESHAPE_CRUISE_MPS` (the followers come
        up beside the leader).
        """
        source, target = self.key.source, self.key.target
        if self.footprint_m(target) >= self.footprint_m(source):
            return RESHAPE_CRUISE_MPS
        a, b = self.book.shapes[source], self.book.shapes[target]
        longest = longest_slide_m(self.book, source, target)
        caps = [v_max_mps]
        for r in a:
            # the slot's velocity in the formation frame at the slide's fastest, and the
            # leader's speed that puts it at v_max over the ground: (v + sx)^2 + sy^2 = v_max^2
            slide = b[r] - a[r]
            sx, sy = slide.x_m * RESHAPE_PEAK_MPS / longest, slide.y_m * RESHAPE_PEAK_MPS / longest
            caps.append(math.sqrt(max(0.0, v_max_mps**2 - sy * sy)) - sx)
        return max(RESHAPE_CRUISE_MPS, min(caps))

    def squeeze(self, squeezed: bool, dt_s: float) -> None:
        """The leader's sonar this step: the way along the route free for itself, but no
        way near it free for the whole shape (`phalanx.agents.behaviours.leader.squeezed`).
        While it lasts no wider shape is taken. Held `SQUEEZE_S`, a group whose fold is
        long (`slide_drive_m` at least `SQUEEZE_FROM_M`) folds at once, to be folded by
        the time it gets there or soon after, the leader's steering holding it where the
        shape as it is does not fit (the map may not show yet that there is no way round).
        """
        # (between two shapes a follower still on its way is no squeeze: not counted)
        self.squeezed_s = self.squeezed_s + dt_s if squeezed and self.key.settled else 0.0
        if self.squeezed_s >= SQUEEZE_S and self.slide_drive_m >= SQUEEZE_FROM_M:
            self.fold()

    def fold(self) -> bool:
        """Fold into the narrowest shape now, if that is another one than the shape in
        effect (and wanted); whether a fold is coming.
        """
        narrowest = self.book.distinct[-1]
        if not self.enabled or self.key.target == narrowest:
            return False
        self.wanted = narrowest
        self._candidate, self._count = narrowest, CONFIRM
        return True

    def fits(self, grid: OccupancyMap, pose: Pose2D, shape: int) -> bool:
        """Whether every slot of `shape`, and of the shape in effect, is clear of the
        map's obstacles with the leader at `pose` and along the next `UNFOLD_AHEAD_M`
        straight on (room to change between them while driving on).
        """
        slots = [*self.book.shapes[shape].values(), *self.book.shapes[self.key.target].values()]
        places = [pose.to_world(Vec2(p.x_m + a, p.y_m)) for a in UNFOLD_AHEAD_M for p in slots]
        return bool(grid.clear_of(places, self.radius_m + FOOTPRINT_MARGIN_M).all())

    def fits_along(self, grid: OccupancyMap, pose: Pose2D, route: Sequence[Vec2]) -> bool:
        """Whether the way is as wide as the scenario's shape (`_wide_at`) with the
        leader at `pose`, and at each of `FITS_ALONG_M` along `route` (its points from
        the leader's on) facing along it there.
        """
        return self._wide_at(grid, list(_poses_along(pose, route, FITS_ALONG_M)))

    def _wide_at(self, grid: OccupancyMap, poses: Sequence[Pose2D]) -> bool:
        """Whether the way is as wide as the scenario's shape with the leader at each of
        `poses`: every slot's place across the heading (its offset to the side, not
        back) is clear of the map's obstacles, the whole row shifted by one of
        `FITS_SHIFTS_M` if need be (the steering keeps the shape off obstacles). The
        group passes where its leader does, so a column fits where its leader's way is
        as wide as a robot.
        """
        across = sorted({p.y_m for p in self.book.shapes[SCENARIO_SHAPE].values()})
        places = [
            at.to_world(Vec2(0.0, y_m + shift_m))
            for at in poses
            for shift_m in FITS_SHIFTS_M
            for y_m in across
        ]
        clear = grid.clear_of(places, self.radius_m + FOOTPRINT_MARGIN_M)
        whole = np.all(clear.reshape(len(poses), len(FITS_SHIFTS_M), len(across)), axis=2)
        return bool(np.any(whole, axis=1).all())

    @cached_property
    def unfold_along_m(self) -> tuple[float, ...]:
        """Where along the route the way must be seen as wide as the scenario's shape
        for the group to unfold into it (m): every metre as far as the leader drives
        on while the slots slide back (`slide_drive_m`), and `UNFOLD_BEYOND_M` more.
        """
        last = math.ceil(self.slide_drive_m + UNFOLD_BEYOND_M)
        return tuple(float(d) for d in range(1, last + 1))

    def unfolds_along(self, grid: OccupancyMap, pose: Pose2D, route: Sequence[Vec2]) -> bool:
        """Whether the map shows room to unfold into the scenario's shape along the
        route: the way as wide as the shape (`_wide_at`, as `fits_along` measures it)
        with the leader at `pose` and at each of `unfold_along_m` along `route`, the
        route that long and the leader's place at each of them seen on the map (not
        merely never sensed).
        """
        along_m = self.unfold_along_m
        poses = list(_poses_along(pose, route, along_m))
        if len(poses) <= len(along_m):
            return False
        xs = np.array([at.x_m for at in poses])
        ys = np.array([at.y_m for at in poses])
        row, col, inside = grid.index(xs, ys)
        if not inside.all() or not grid.seen[row, col].all():
            return False
        return self._wide_at(grid, poses)

    def decide(
        self,
        grid: OccupancyMap | None,
        pose: Pose2D,
        goal: Vec2,
        t_s: float,
        route: Sequence[Vec2] = (),
    ) -> None:
        """Weigh the shapes (every `DECIDE_S`): the widest whose route is about as good as
        the best; a change is wanted once it has come out `CONFIRM` times running, not
        within `DWELL_S` of the last reshape, and a wider shape only if it fits here and
        on ahead (`fits`). `route` is the leader's (`scenario_fits` looks along it).
        While the slots slide it only gauges the way (`gauge`).
        """
        if not self.enabled or grid is None or t_s - self._decided_s < DECIDE_S:
            return
        if not self.key.settled:
            # (a slide under way is turned back only by the sonar's fold)
            self.gauge(grid, pose, goal, t_s, route)
            return
        self._decided_s = self._gauged_s = t_s
        best = self._best(grid, pose.position, goal)
        self.scenario_fits = self._fits_now(grid, pose, route, lambda: best)
        if best is None or t_s - self._settled_s < DWELL_S:
            self._count = 0
            return
        wider = self.footprint_m(best) > self.footprint_m(self.key.target)
        if wider and (self.squeezed_s > 0.0 or not self._room_for(grid, pose, best, route)):
            best = self.key.target
        self._count = self._count + 1 if best == self._candidate else 1
        self._candidate = best
        if self._count >= CONFIRM:
            self.wanted = best

    def gauge(
        self,
        grid: OccupancyMap | None,
        pose: Pose2D,
        goal: Vec2,
        t_s: float,
        route: Sequence[Vec2] = (),
    ) -> None:
        """Whether the scenario's shape fits the way (`scenario_fits`, as `decide` has
        it), every `DECIDE_S`, where the leader weighs no shape: while the slots slide,
        or while it does anything but navigate (the time the shape fits is measured all
        the way, not held from the last weighing). It changes nothing the group does.
        """
        if not self.enabled or grid is None or t_s - self._gauged_s < DECIDE_S:
            return
        self._gauged_s = t_s
        self.scenario_fits = self._fits_now(
            grid, pose, route, lambda: self._best(grid, pose.position, goal)
        )

    def _fits_now(
        self,
        grid: OccupancyMap,
        pose: Pose2D,
        route: Sequence[Vec2],
        best: Callable[[], int | None],
    ) -> bool:
        """What `scenario_fits` says: the way as wide as the scenario's shape along the
        route (`fits_along`), and that shape the best (`best`, the shape `_best` weighs
        best or has weighed; asked only once the width is there, the cheaper check, which
        mostly settles it while folded).
        """
        return self.fits_along(grid, pose, route) and best() == SCENARIO_SHAPE

    def _room_for(
        self, grid: OccupancyMap, pose: Pose2D, shape: int, route: Sequence[Vec2]
    ) -> bool:
        """Whether the group may widen into `shape` here: the map shows the way wide
        enough for the scenario's shape as far as the unfold takes (`unfolds_along`),
        or every slot clear straight on (`fits`).
        """
        if shape == SCENARIO_SHAPE and self.unfolds_along(grid, pose, route):
            return True
        return self.fits(grid, pose, shape)

    def _best(self, grid: OccupancyMap, start: Vec2, goal: Vec2) -> int | None:
        """The widest shape whose route to `goal` is about as good as the shortest of any
        shape's (`_within_detour`); None if no shape has one. The scenario's shape is
        planned first: a route within the detour of the fewest moves to the goal
        (`OccupancyMap.fewest_m`) is within it of every route, and settles it.
        """
        shapes = self.book.distinct
        scenario_m = grid.route_length_m(start, goal, footprint_m=self.footprint_m(shapes[0]))
        if scenario_m is not None and scenario_m <= _within_detour(grid.fewest_m(start, goal)):
            return shapes[0]
        lengths: dict[int, float] = {} if scenario_m is None else {shapes[0]: scenario_m}
        for shape in shapes[1:]:
            length_m = grid.route_length_m(start, goal, footprint_m=self.footprint_m(shape))
            if length_m is not None:
                lengths[shape] = length_m
        if not lengths:
            return None
        longest = _within_detour(min(lengths.values()))
        return next(s for s in shapes if lengths.get(s, math.inf) <= longest)

    def settled_at(self, t_s: float) -> None:
        """A reshape is over (the dwell time runs from here)."""
        self._settled_s = t_s
        self._count = 0


def slide_s(book: ShapeBook, source: int, target: int) -> float:
    """How long a reshape from `source` to `target` slides the slots (s): the longest
    slide at `RESHAPE_MPS`, and at least `RESHAPE_MIN_S`.
    """
    return max(RESHAPE_MIN_S, longest_slide_m(book, source, target) / RESHAPE_MPS)


def longest_slide_m(book: ShapeBook, source: int, target: int) -> float:
    """How far the slot that moves furthest slides from `source` to `target` (m)."""
    a, b = book.shapes[source], book.shapes[target]
    return max((b[r] - a[r]).norm() for r in a)


def _within_detour(shortest_m: float) -> float:
    """The longest route as good as the best when the best is `shortest_m` long (m)."""
    return shortest_m * DETOUR_SHARE + DETOUR_M


def _poses_along(
    pose: Pose2D, route: Sequence[Vec2], distances_m: Sequence[float]
) -> Iterator[Pose2D]:
    """`pose`, then the route's first point at least each of `distances_m` along it from
    `pose`, facing along the route there (as far as the route goes).
    """
    yield pose
    points = (pose.position, *route)
    along_m, k = 0.0, 0
    for distance_m in distances_m:
        while along_m < distance_m and k + 1 < len(points):
            k += 1
            along_m += (points[k] - points[k - 1]).norm()
        if along_m < distance_m:
            return
        before = points[max(0, k - ROUTE_HEADING_SPAN)]
        after = points[min(len(points) - 1, k + ROUTE_HEADING_SPAN)]
        heading = math.atan2(after.y_m - before.y_m, after.x_m - before.x_m)
        yield Pose2D(points[k].x_m, points[k].y_m, heading)


class Drive(Protocol):
    """What a reshaping leader drives on with: its navigation behaviour."""

    @property
    def has_goal(self) -> bool: ...  # noqa: D102

    def command(self, moment: Moment) -> Twist2D: ...  # noqa: D102

    @property
    def drove_forward(self) -> Twist2D | None: ...  # noqa: D102


class Reshape(Behaviour):
    """RESHAPE (the leader): drive on (`drive`, the navigation behaviour, capped at
    `ShapeKeeper.drive_cap_mps`; standing still without one) while every slot slides to
    the new shape's.
    """

    def __init__(
        self, keeper: ShapeKeeper, shape: Shape, *, dt_s: float, drive: Drive | None = None
    ) -> None:
        self.keeper, self.shape, self.dt_s, self.drive = keeper, shape, dt_s, drive
        self.duration_s = RESHAPE_MIN_S
        self.done_s: float | None = None

    @property
    def reshaped(self) -> bool:
        """The new shape is reached and the followers had time to settle in it."""
        return self.done_s is not None and self._since_done >= SETTLE_S

    def enter(self, moment: Moment) -> None:
        """Start sliding from the shape in effect to the one wanted (or carry on a slide
        that was interrupted).
        """
        keeper = self.keeper
        if keeper.key.settled:
            keeper.key = ShapeKey(keeper.key.target, keeper.wanted, 0.0)
        self.duration_s = slide_s(keeper.book, keeper.key.source, keeper.key.target)
        self.done_s = None
        self._since_done = 0.0

    def command(self, moment: Moment) -> Twist2D:
        """The shape's slide moves on a step (back the way it came if the shape it left
        is wanted again: a fold called for half-way through an unfold); the leader
        drives on, slower than navigation would where the followers need it.
        """
        keeper = self.keeper
        if not keeper.key.settled and keeper.wanted == keeper.key.source:
            keeper.key = ShapeKey(keeper.key.target, keeper.key.source, 1.0 - keeper.key.morph)
        self.slide(moment)
        self.drove_forward = None
        if self.drive is None or not self.drive.has_goal:
            return ZERO_TWIST
        twist = self.drive.command(moment)
        self.drove_forward = self.drive.drove_forward
        return _capped(twist, keeper.drive_cap_mps(self.shape.limits.v_max_mps))

    def slide(self, moment: Moment) -> None:
        """The slide moves a step on to its target; once there, the settling time runs."""
        keeper = self.keeper
        if not keeper.key.settled:
            morph = min(1.0, keeper.key.morph + self.dt_s / self.duration_s)
            keeper.key = ShapeKey(keeper.key.source, keeper.key.target, morph)
        elif self.done_s is None:
            self.done_s = moment.t_s
        else:
            self._since_done += self.dt_s

    def leave(self, moment: Moment) -> None:
        """Done (or interrupted): the next change waits its dwell time."""
        if self.keeper.key.settled:
            self.keeper.settled_at(moment.t_s)
            self.keeper.wanted = self.keeper.key.target


class Arrived(Behaviour):
    """ARRIVED (the leader): stand still. A slide under way when the leader got there
    goes on to its end, so the group stops in the shape it was sliding to, not half-way
    between two; no other starts.
    """

    def __init__(self, reshape: Reshape) -> None:
        self.reshape = reshape
        self.sliding = False  # it arrived between two shapes

    def enter(self, moment: Moment) -> None:
        """Note whether a slide is under way."""
        self.sliding = not self.reshape.keeper.key.settled

    def command(self, moment: Moment) -> Twist2D:
        """Zero; the slide, if one is under way, a step on."""
        if not self.reshape.keeper.key.settled:
            self.reshape.slide(moment)
        return ZERO_TWIST

    def leave(self, moment: Moment) -> None:
        """After a slide: as a reshape's end (the next change waits its dwell time)."""
        if self.sliding:
            self.reshape.leave(moment)


def _capped(twist: Twist2D, v_max_mps: float) -> Twist2D:
    """`twist` slowed to at most `v_max_mps`, on the same curve."""
    if abs(twist.v_mps) <= v_max_mps:
        return twist
    share = v_max_mps / abs(twist.v_mps)
    return Twist2D(twist.v_mps * share, twist.omega_radps * share)
