"""Leader behaviours (the navigation layer of whichever robot leads): the scripted
profile of the paper's runs, go-to-goal and wander with reactive steering, the deadlock
escape (back off in formation, then turn), and an operator's teleoperation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from phalanx.agents.behaviours.base import Behaviour, Moment, turn_on_spot
from phalanx.agents.memory import BlockedTimers, Progress, Route
from phalanx.agents.navigation import (
    REORIENT_RAD,
    Clearances,
    Course,
    NavSettings,
    RecentEchoes,
    RoutePlanner,
    ScriptedProfile,
    Steering,
    WanderHeading,
    bearing_rad,
    centring_rad,
    free_heading_near,
    heading_index,
    open_side,
    reverse_twist,
    rigid_limit,
    steer,
)
from phalanx.agents.reshape import ShapeKeeper
from phalanx.agents.shape import Shape
from phalanx.core.config import LeaderProfile, NavigationConfig
from phalanx.core.geometry import ZERO_TWIST, Pose2D, Twist2D, Vec2, integrate_unicycle, wrap_angle
from phalanx.core.limits import KinematicLimits
from phalanx.core.robot import Odometry

# A turn on the spot is done within this of the heading it was for.
REORIENTED_RAD = math.radians(10.0)
# Pure pursuit distance of the deadlock reverse along the recorded path.
REVERSE_LOOKBACK_M = 0.6
# The fixed deadlock reverse first turns the shape back to the way it came in (measured
# over this much path) to within this, for at most this long; only from at most this far
# round, which the shape has just swept through (a larger turn back is not known free).
CAME_IN_OVER_M = 2.0
REALIGNED_RAD = math.radians(1.0)
REALIGN_MAX_S = 20.0
REALIGN_MAX_RAD = math.radians(45.0)
# A deadlock's turn towards the route ends on a heading free for this many times the
# range an obstacle blocks at (`deadlock.obstacle_range_m`).
TURN_ROOM = 2.0
# An obstacle nearer ahead than this share of the lookahead lets the leader bend its
# course as tight as the shape allows.
TIGHT_AHEAD_SHARE = 0.5
# The leader's sonar squeezes the shape only where no candidate heading within this many
# steps of the route's (7.5 deg each) is free for the whole shape.
SQUEEZE_WINDOW = 2
# The navigator steers by the echoes of the last this long (s).
RECENT_ECHOES_S = 1.0
# While a robot of the group is off its slot, no slot may need more than this share of
# what it may otherwise (`rigid_limit`): on a bend, a robot trailing an outer slot that
# needs nearly the speed limit would have no speed left to catch up with.
CATCH_UP_SHARE = 0.8


class Scripted(Behaviour):
    """NAVIGATE with a `leader_profile`: the paper's piecewise constant twists, on the
    group's profile clock (so a new leader carries on where the last one was), kept to
    the path they describe.

    The script's twists, integrated from where the robot was when it took up (or
    resumed) the script, are its reference; a tracking law (Kanayama's) corrects what
    the robot did not do as asked: its ramps to each new speed, a firmware's latency, a
    simulator whose clock runs slow (AMRISim's loses a few ms each 100 ms update), a
    tyre a little small. Where the robot does as asked the correction is nil.
    """

    def __init__(
        self, profile: LeaderProfile, *, progress: Progress, course: Course, dt_s: float
    ) -> None:
        self.profile = ScriptedProfile(profile)
        self.progress, self.course, self.dt_s = progress, course, dt_s
        self._reference: Pose2D | None = None  # where the script has the robot now

    def enter(self, moment: Moment) -> None:
        """Taking up the script: its path goes on from here."""
        self._reference = moment.pose

    def command(self, moment: Moment) -> Twist2D:
        """The script's twist now, corrected towards its path; the profile clock moves
        on a step.
        """
        twist = self.profile.twist_at(self.progress.profile_s)
        reference = self._reference or moment.pose
        self._reference = integrate_unicycle(reference, twist, self.dt_s)
        self.progress.profile_s += self.dt_s
        self.drove_forward = twist
        return keep_to(reference, moment.pose, twist)


# Kanayama's tracking gains (1/s, 1/m^2, 1/m): a lag along the path closes in about 2 s,
# a heading or lateral error in about 3 s at the paper's 0.15 m/s.
TRACK_ALONG_PER_S = 0.5
TRACK_ACROSS_PER_M2 = 4.0
TRACK_HEADING_PER_M = 4.0


def keep_to(reference: Pose2D, pose: Pose2D, twist: Twist2D) -> Twist2D:
    """`twist`, the reference's, corrected to bring the robot at `pose` onto
    `reference` (Kanayama, Kimura, Miyazaki & Noguchi 1990).
    """
    error = pose.relative(reference)  # the reference in the robot's frame
    v, w = twist.v_mps, twist.omega_radps
    along = v * math.cos(error.theta_rad) + TRACK_ALONG_PER_S * error.x_m
    turn = w + v * (
        TRACK_ACROSS_PER_M2 * error.y_m + TRACK_HEADING_PER_M * math.sin(error.theta_rad)
    )
    return Twist2D(along, turn)


@dataclass(frozen=True, slots=True)
class SteeredParts:
    """What every steered behaviour of a leader (`GoToGoal`, `Wander`) is made of, made
    once and shared: the navigation settings, the shape and the limits it steers within,
    and the memories they share (the steering, the leader's course).
    """

    settings: NavSettings
    shape: Shape
    limits: KinematicLimits
    steering: Steering
    course: Course


class Steered(Behaviour):
    """Reactive navigation for a formation: head the way `desired` says, round what the
    sonar shows, no tighter than the shape allows, slowing near obstacles and while
    robots of the group are off their slots. Subclasses say where to head for.
    """

    def __init__(self, parts: SteeredParts) -> None:
        self.nav = parts.settings.nav
        self.scripted = parts.settings.plan == "scripted"
        self.shape, self.limits = parts.shape, parts.limits
        self.steering, self.course = parts.steering, parts.course
        self.keeper: ShapeKeeper | None = None  # (a leader that may change the shape)
        self.drove_forward: Twist2D | None = None
        self.dt_s = parts.settings.dt_s
        self.recent = RecentEchoes(RECENT_ECHOES_S)

    def desired(self, moment: Moment) -> tuple[float, float]:
        """The heading wanted (body frame, rad) and the distance to go (m)."""
        raise NotImplementedError

    def command(self, moment: Moment) -> Twist2D:
        """Finish a turn on the spot, or steer towards `desired` round obstacles."""
        self.drove_forward = None
        desired, dist_m = self.desired(moment)
        speed = min(self.nav.cruise_mps, 0.5 * dist_m + 0.02)
        if moment.others_busy:
            speed *= self.nav.slowdown  # give robots off their slots a chance to catch up
        turning = self._finish_turn(moment)
        if turning is not None:
            return turning
        return self._steer(moment, desired, dist_m, speed)

    def _finish_turn(self, moment: Moment) -> Twist2D | None:
        """A turn on the spot under way, until it faces the heading it was for."""
        points, pose = moment.sensing.points, moment.pose
        if self.steering.turn_to_rad is not None and not self.shape.sweep_clear(points):
            self.steering.turn_to_rad = None  # no room to swing the shape round here after all
        if self.steering.turn_to_rad is None:
            return None
        error = wrap_angle(self.steering.turn_to_rad - pose.theta_rad)
        if abs(error) > REORIENTED_RAD:
            return turn_on_spot(error, self.nav.heading_gain_per_s, self.shape.turn_rate_radps())
        self.steering.turn_to_rad = None
        return None

    def _steer(self, moment: Moment, desired: float, dist_m: float, speed: float) -> Twist2D:
        pose, points = moment.pose, moment.sensing.points
        chosen_rad = self.steering.chosen_rad
        previous = None if chosen_rad is None else wrap_angle(chosen_rad - pose.theta_rad)
        whole_shape = moment.view.is_leader and not self.scripted
        recent = self.recent.with_recent(pose, points, moment.t_s)
        clearances = self.shape.clearances(recent, moment.view.live, whole_shape=whole_shape)
        room_to_turn = self.shape.sweep_clear(points)
        if self.keeper is not None:
            self.keeper.squeeze(squeezed(clearances, desired, dist_m, self.nav), self.dt_s)
        twist, chosen = steer(
            desired + centring_rad(clearances),
            clearances,
            nav=self.nav,
            speed_mps=speed,
            stop_gap_m=self.shape.stop_gap_m(),
            need_m=min(self.nav.lookahead_m, dist_m + self.shape.radius_m),
            omega_max_radps=self.shape.turn_rate_radps(),
            previous_rad=previous,
            min_radius_m=self._turn_radius_m(clearances),
            reach_rad=math.pi if room_to_turn else REORIENT_RAD,
        )
        self.steering.chosen_rad = pose.theta_rad + chosen
        if twist.v_mps == 0.0 and twist.omega_radps != 0.0 and room_to_turn:
            self.steering.turn_to_rad = self.steering.chosen_rad
        lagging = any(not f.formed for f in moment.view.live.values())
        v_max = self.limits.v_max_mps * (CATCH_UP_SHARE if lagging else 1.0)
        twist = rigid_limit(twist, self.shape.follower_slots, v_max)
        self.drove_forward = twist
        return twist

    def _turn_radius_m(self, clear: Clearances) -> float:
        """The tightest arc to lead along: `min_turn_radius_m` (the followers keep their
        slots best on gentle bends), or as tight as the shape allows with an obstacle
        close ahead (where a gentle bend would not get round it).
        """
        if clear.ahead_m() < TIGHT_AHEAD_SHARE * self.nav.lookahead_m:
            return self.shape.turn_radius_m()
        return self.nav.min_turn_radius_m


def squeezed(clear: Clearances, desired_rad: float, dist_m: float, nav: NavigationConfig) -> bool:
    """The way towards `desired_rad` is free for the leader alone, and no way within
    `SQUEEZE_WINDOW` headings of it is free for the shape: the shape would have to
    swerve further off its route than that to stay whole (within it, the steering takes
    the way free for the shape).
    """
    i = heading_index(desired_rad)
    need = min(nav.lookahead_m, dist_m)
    if clear.narrow[i] < need:
        return False
    window = np.arange(i - SQUEEZE_WINDOW, i + SQUEEZE_WINDOW + 1) % clear.wide.size
    return bool((clear.wide[window] < need).all())


class GoToGoal(Steered):
    """NAVIGATE with waypoints: along the route to the next one (or first to the escape
    point a dead end left), round obstacles.
    """

    def __init__(
        self,
        parts: SteeredParts,
        *,
        planner: RoutePlanner,
        progress: Progress,
        route: Route,
        keeper: ShapeKeeper | None = None,
    ) -> None:
        super().__init__(parts)
        self.planner, self.progress, self.route, self.keeper = planner, progress, route, keeper

    @property
    def has_goal(self) -> bool:
        """Whether there is a waypoint (or an escape point) left to go to."""
        waypoints = self.route.waypoints
        return self.course.escape is not None or self.progress.waypoint < len(waypoints)

    def desired(self, moment: Moment) -> tuple[float, float]:
        """Towards the route's next point."""
        pose = moment.pose
        goal = self.course.escape or Vec2(*self.route.waypoints[self.progress.waypoint])
        dist_m = (goal - pose.position).norm()
        return bearing_rad(pose, self.planner.towards(pose, goal, moment.t_s)), dist_m


class Wander(Steered):
    """WANDER: cruise along a heading that changes now and then (seeded), round obstacles."""

    def __init__(self, parts: SteeredParts, *, seed: int) -> None:
        super().__init__(parts)
        self.heading = WanderHeading(parts.settings.nav, seed)

    def desired(self, moment: Moment) -> tuple[float, float]:
        """The wander heading, with nowhere in particular to get to."""
        heading = self.heading.heading(moment.pose, moment.t_s)
        return wrap_angle(heading - moment.pose.theta_rad), math.inf


class DeadlockReverse(Behaviour):
    """DEADLOCK_REVERSE (the paper's section 3.2): stand still `pause_s` (the followers
    settle on their slots; with `pause_until_settled`, only until every follower heard
    says it has), then back the group off in formation: along the path it came
    (`path`), the arc just driven (`retrace`) or straight back (`fixed`, a navigating
    group first turning back to the way it came in).
    """

    def __init__(
        self, settings: NavSettings, *, shape: Shape, course: Course, progress: Progress
    ) -> None:
        self.deadlock = settings.deadlock
        self.nav = settings.nav
        self.navigating = settings.plan == "goto"
        self.shape, self.course, self.progress = shape, course, progress
        self.pausing = False  # standing still before it backs off
        self.reversed_m = 0.0
        self.path_used_up = False  # backed along all of the recorded path
        self._entered_s = 0.0
        self._realigned_s = -math.inf  # when the turn back was done
        self._backing = False  # the pause is over

    def enter(self, moment: Moment) -> None:
        """A new deadlock at this waypoint: count it, start from standing."""
        self._entered_s = self._realigned_s = moment.t_s
        self._backing = False
        self.reversed_m = 0.0
        self.path_used_up = False
        self.progress.deadlocks += 1

    def observe(self, odometry: Odometry, previous: Odometry) -> None:
        """Count the ground backed over."""
        self.reversed_m += (odometry.pose.position - previous.pose.position).norm()

    def command(self, moment: Moment) -> Twist2D:
        """Turn back, pause, then back off."""
        if not self._backing:
            realign = self._realign(moment)
            if realign is not None:
                self.pausing = True
                self._realigned_s = moment.t_s
                return realign
            self._backing = not self._stands_on(moment)
        self.pausing = not self._backing
        if self.pausing:
            return ZERO_TWIST  # stand still first: the followers settle on their slots
        if self.deadlock.reverse_mode != "path":
            return reverse_twist(self.deadlock, moment.last_forward)
        speed = self.deadlock.reverse_speed_mps
        twist = self.course.crumbs.back_along(moment.pose, speed, REVERSE_LOOKBACK_M)
        if twist is None:  # backed along all the ground it knows: go no further
            self.path_used_up = True
            return ZERO_TWIST
        return twist

    def _stands_on(self, moment: Moment) -> bool:
        """Whether the pause goes on: `pause_s` since the turn back, unless (with
        `pause_until_settled`) every follower heard has said since that it has settled.
        """
        since_s = self._realigned_s
        if moment.t_s - since_s >= self.deadlock.pause_s - 1e-9:
            return False
        if not self.deadlock.pause_until_settled:
            return True
        me = moment.view.leader_id
        followers = [f for r, f in moment.view.live.items() if r != me]
        return not followers or not all(f.settled and f.stamp_s > since_s for f in followers)

    def _realign(self, moment: Moment) -> Twist2D | None:
        """A navigating group caught in a deadlock while turning: turn the shape back to
        the way it came in before backing out straight (else it backs out diagonally).
        """
        if self.deadlock.reverse_mode != "fixed" or not self.navigating:
            return None
        if moment.t_s - self._realigned_s >= self.deadlock.pause_s:
            return None  # backing out already
        came_in = self.course.crumbs.heading_in_rad(CAME_IN_OVER_M)
        if came_in is None or moment.t_s - self._entered_s > REALIGN_MAX_S:
            return None
        error = wrap_angle(came_in - moment.pose.theta_rad)
        if not REALIGNED_RAD < abs(error) <= REALIGN_MAX_RAD:
            return None
        return turn_on_spot(
            error, self.nav.heading_gain_per_s, self.shape.turn_rate_radps(rigid=True)
        )


class DeadlockTurn(Behaviour):
    """DEADLOCK_TURN: turn on the spot towards the route if the map has one, else towards
    the more open side by `turn_away_deg` per deadlock at this waypoint; then (without a
    map) make for a point `escape_distance_m` along the new heading first.
    """

    def __init__(
        self,
        settings: NavSettings,
        *,
        shape: Shape,
        planner: RoutePlanner,
        progress: Progress,
        route: Route,
        course: Course,
        blocked: BlockedTimers,
    ) -> None:
        self.deadlock, self.nav = settings.deadlock, settings.nav
        self.navigating = settings.plan == "goto"
        self.shape, self.planner, self.progress, self.course = shape, planner, progress, course
        self.route, self.blocked = route, blocked
        self.side = 1
        self.target_rad = 0.0
        self.turned_rad = 0.0

    @property
    def turned(self) -> bool:
        """Whether the turn is done."""
        return self.turned_rad >= self.target_rad - 1e-3

    def enter(self, moment: Moment) -> None:
        """Choose the side and how far to turn."""
        pose = moment.pose
        self.side = open_side(moment.sensing.points, half_width_m=self.shape.half_width_m)
        angle = math.radians(self.deadlock.turn_away_deg) * max(1, self.progress.deadlocks)
        if self.navigating and self.planner.map is not None:
            self.planner.forget_carrot()
            waypoints = self.route.waypoints
            goal = Vec2(*waypoints[min(self.progress.waypoint, len(waypoints) - 1)])
            towards = free_heading_near(
                moment.sensing.points,
                bearing_rad(pose, self.planner.towards(pose, goal, moment.t_s)),
                half_width_m=self.shape.half_width_m,
                room_m=TURN_ROOM * self.deadlock.obstacle_range_m,
            )
            self.side, angle = (1 if towards >= 0.0 else -1), abs(towards)
        self.target_rad = min(math.pi, angle)
        self.turned_rad = 0.0

    def leave(self, moment: Moment) -> None:
        """A new heading: blocked only if blocked again; without a map, leave the dead
        end along it before making for the goal.
        """
        self.blocked.reset()
        if self.navigating and self.planner.map is None:
            ahead = Vec2(self.deadlock.escape_distance_m, 0.0)
            self.course.escape = moment.pose.to_world(ahead)

    def observe(self, odometry: Odometry, previous: Odometry) -> None:
        """Count the angle turned."""
        self.turned_rad += abs(wrap_angle(odometry.pose.theta_rad - previous.pose.theta_rad))

    def command(self, moment: Moment) -> Twist2D:
        """Turn on the spot, as fast as the shape allows."""
        return Twist2D(0.0, self.side * self.shape.turn_rate_radps(rigid=True))


class Teleop(Behaviour):
    """TELEOP: drive as the operator asks (the step's `Moment.operator`), no faster than
    every slot of the shape can keep up with (`rigid_limit`, as the steered behaviours
    lead); the spacing filter, the contact guard and the limiter then hold it like any
    other command, and the emergency stop outranks it.
    """

    def __init__(self, shape: Shape, limits: KinematicLimits) -> None:
        self.shape, self.limits = shape, limits

    def command(self, moment: Moment) -> Twist2D:
        """The operator's twist, kept to what the shape can follow."""
        twist = moment.operator or ZERO_TWIST
        return rigid_limit(twist, self.shape.follower_slots, self.limits.v_max_mps)
