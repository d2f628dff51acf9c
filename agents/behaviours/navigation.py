"""The navigation layer's motion: the leader's scripted profile (the paper's piecewise
constant velocities), go-to-goal and wander with reactive steering from the sonar
ring, the deadlock reverse and turn, and a follower's way round an obstacle.

Every function turns what the robot knows into an unsaturated twist; the limiter comes
after, as for the formation controllers.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from phalanx.agents.perception import HEADINGS_RAD, FloatArray, choose_heading
from phalanx.core.config import DeadlockConfig, LeaderProfile, NavigationConfig, Scenario
from phalanx.core.geometry import ZERO_TWIST, Pose2D, Twist2D, Vec2, wrap_angle

Plan = Literal["scripted", "goto", "wander"]


def plan_of(scenario: Scenario) -> Plan:
    """What a leader of `scenario` does: its script, go to waypoints, or wander."""
    if scenario.leader_profile is not None:
        return "scripted"
    return "goto" if scenario.navigation.waypoints else "wander"


# Fraction of the run's speed limit a follower's slot may need: the rest is its margin
# to catch up. The leader slows a turn so that no slot of the rigid shape needs more.
RIGID_SPEED_SHARE = 0.9
# A navigator slows near obstacles but no slower than this until it must stop.
CREEP_MPS = 0.05
# A formation leader whose way round is further off than this turns on the spot first.
REORIENT_RAD = math.radians(45.0)
# Corridor centring: side clearances within this range (m) bias the heading, by this
# gain (rad per m of imbalance) up to this much.
CENTRING_RANGE_M = 1.5
CENTRING_GAIN_PER_M = 0.5
CENTRING_MAX_RAD = math.radians(15.0)
# Half the spacing of the candidate headings (`HEADINGS_RAD`).
HALF_STEP_RAD = float(HEADINGS_RAD[1] - HEADINGS_RAD[0]) / 2
# The deadlock reverse never retraces a tighter arc than this (a crawl's curvature is noise).
RETRACE_MIN_RADIUS_M = 2.0


class ScriptedProfile:
    """Piecewise constant twist over profile time (s); zero after the end unless repeating."""

    def __init__(self, profile: LeaderProfile) -> None:
        self._segments = profile.segments
        self._repeat = profile.repeat
        self._total_s = sum(s.duration_s for s in profile.segments)

    def twist_at(self, profile_time_s: float) -> Twist2D:
        """The scripted twist at `profile_time_s` seconds into the profile."""
        t = profile_time_s % self._total_s if self._repeat else profile_time_s
        for segment in self._segments:
            if t < segment.duration_s:
                return Twist2D(segment.v_mps, math.radians(segment.omega_degps))
            t -= segment.duration_s
        return ZERO_TWIST


def reverse_twist(deadlock: DeadlockConfig, last_forward: Twist2D) -> Twist2D:
    """The deadlock reverse (section 3.2): straight back (`fixed`), or back along the arc
    just driven (`retrace`: same curvature, the path known to be free).
    """
    speed = deadlock.reverse_speed_mps
    if deadlock.reverse_mode != "retrace" or abs(last_forward.v_mps) < 1e-6:
        return Twist2D(-speed, math.radians(deadlock.reverse_omega_degps))
    curvature_per_m = last_forward.omega_radps / last_forward.v_mps
    limit = 1.0 / RETRACE_MIN_RADIUS_M
    curvature_per_m = max(-limit, min(limit, curvature_per_m))
    return Twist2D(-speed, -speed * curvature_per_m)


class Breadcrumbs:
    """The leader's recent path (odometry positions every `spacing_m`), to back along."""

    def __init__(self, length_m: float, spacing_m: float = 0.05) -> None:
        self.spacing_m = spacing_m
        self._points: deque[Vec2] = deque(maxlen=max(2, math.ceil(length_m / spacing_m) + 2))

    def __len__(self) -> int:
        return len(self._points)

    def drop(self, position: Vec2) -> None:
        """Record `position` if it is `spacing_m` from the last one."""
        if not self._points or (position - self._points[-1]).norm() >= self.spacing_m:
            self._points.append(position)

    def clear(self) -> None:
        """Forget the path (a new leader starts its own)."""
        self._points.clear()

    def heading_in_rad(self, over_m: float) -> float | None:
        """The direction the path came in over its last `over_m` (world frame), or None
        when it is shorter than that.
        """
        if not self._points:
            return None
        last = self._points[-1]
        start = next((p for p in reversed(self._points) if (last - p).norm() >= over_m), None)
        if start is None:
            return None
        return math.atan2(last.y_m - start.y_m, last.x_m - start.x_m)

    def back_along(self, pose: Pose2D, speed_mps: float, lookback_m: float) -> Twist2D | None:
        """Pure pursuit backwards to the recorded point `lookback_m` behind, eating the
        path as the robot passes it; None once it is used up.
        """
        pts = self._points
        while pts and (
            pose.to_body(pts[-1]).x_m > -0.02 or (pts[-1] - pose.position).norm() < 0.05
        ):
            pts.pop()  # reached or passed
        if not pts:
            return None
        target = next(
            (p for p in reversed(pts) if (p - pose.position).norm() >= lookback_m), pts[0]
        )
        local = pose.to_body(target)
        d2 = max(local.x_m**2 + local.y_m**2, 1e-6)
        # Mirror the robot to face backwards: forward pure pursuit there, same yaw rate.
        omega = -2.0 * speed_mps * local.y_m / d2
        limit = speed_mps / RETRACE_MIN_RADIUS_M
        return Twist2D(-speed_mps, max(-limit, min(limit, omega)))


def bearing_rad(pose: Pose2D, point: Vec2) -> float:
    """Direction of `point` from `pose`, in the body frame (rad, counter-clockwise)."""
    local = pose.to_body(point)
    return math.atan2(local.y_m, local.x_m)


def heading_index(heading_rad: float) -> int:
    """Index of the candidate heading (`HEADINGS_RAD`) nearest `heading_rad` (body
    frame, any number of turns).
    """
    off = np.abs(np.mod(HEADINGS_RAD - heading_rad + math.pi, 2 * math.pi) - math.pi)
    return int(np.argmin(off))


AHEAD_INDEX = heading_index(0.0)


@dataclass(frozen=True, slots=True)
class Clearances:
    """Free distance (m) along every candidate heading, the formation's and own; and the
    formation's free room sliding sideways, left and right (for centring).
    """

    wide: FloatArray
    narrow: FloatArray
    left_m: float = math.inf
    right_m: float = math.inf

    def ahead_m(self) -> float:
        """Own free distance straight ahead."""
        return float(self.narrow[AHEAD_INDEX])

    def along_m(self, heading_rad: float) -> float:
        """Own free distance along the candidate heading nearest `heading_rad`."""
        return float(self.narrow[heading_index(heading_rad)])


def centring_rad(clear: Clearances) -> float:
    """A small heading bias away from the nearer side wall (the corridor-centring
    behaviour of behaviour-based robots): the whole shape's free way sideways, left
    against right, where either is within `CENTRING_RANGE_M`.
    """
    left = min(clear.left_m, CENTRING_RANGE_M)
    right = min(clear.right_m, CENTRING_RANGE_M)
    if left >= CENTRING_RANGE_M and right >= CENTRING_RANGE_M:
        return 0.0
    bias = CENTRING_GAIN_PER_M * (left - right)
    return max(-CENTRING_MAX_RAD, min(CENTRING_MAX_RAD, bias))


def speed_factor(gap_m: float, *, stop_gap_m: float, slow_range_m: float) -> float:
    """1 with room ahead, falling linearly to 0 at `stop_gap_m` from an obstacle."""
    return min(1.0, max(0.0, (gap_m - stop_gap_m) / slow_range_m))


def steer(
    desired_rad: float,
    clear: Clearances,
    *,
    nav: NavigationConfig,
    speed_mps: float,
    stop_gap_m: float,
    need_m: float,
    omega_max_radps: float,
    window_rad: float = math.pi / 2,
    previous_rad: float | None = None,
    min_radius_m: float = 0.0,
    reach_rad: float = math.pi,
) -> tuple[Twist2D, float]:
    """Head for `desired_rad` (body frame) round obstacles: the nearest heading whose way
    is free (`choose_heading`), turn towards it, slow down as it gets tighter (but keep
    creeping until `stop_gap_m`, so a dead end is found rather than approached forever).
    Turns are no tighter than `min_radius_m` (0: on the spot if need be). Returns the
    twist and the chosen heading (body frame).
    """
    index = choose_heading(
        desired_rad,
        wide=clear.wide,
        narrow=clear.narrow,
        need_m=need_m,
        window_rad=window_rad,
        previous_rad=previous_rad,
        reach_rad=reach_rad,
    )
    heading = float(HEADINGS_RAD[index])
    if min_radius_m > 0.0 and abs(heading) > REORIENT_RAD:
        # Far off course: stop and turn on the spot (the shape swings round its leader)
        # rather than sweep a wide arc through whatever made the detour necessary.
        return Twist2D(0.0, math.copysign(omega_max_radps, heading)), heading
    ahead_m = clear.ahead_m()
    room = speed_factor(ahead_m, stop_gap_m=stop_gap_m, slow_range_m=nav.lookahead_m / 2)
    v = speed_mps * room
    if min_radius_m <= 0.0:
        v *= max(0.0, math.cos(heading))  # a lone robot turns first, then goes
    if ahead_m > stop_gap_m and math.cos(heading) > 0.0:
        v = max(v, min(speed_mps, CREEP_MPS))
    omega_max = omega_max_radps
    if min_radius_m > 0.0:
        # A rigid shape turning about a point inside itself twists its followers round.
        omega_max = min(omega_max, v / min_radius_m)
    omega = max(-omega_max, min(omega_max, nav.heading_gain_per_s * _aim_rad(heading, desired_rad)))
    return Twist2D(v, omega), heading


def _aim_rad(heading_rad: float, desired_rad: float) -> float:
    """What to turn towards: `desired_rad` itself when it lies within half a candidate's
    step of the chosen heading (the way there is the one found free), else the chosen
    heading. Candidates 7.5 deg apart would otherwise have a leader on a nearly straight
    course switch between straight on and a full-rate bend, and a shape's far slots
    (whose direction moves by about `x dw / v`) swing from side to side with it.
    """
    off = wrap_angle(desired_rad - heading_rad)
    return heading_rad + off if abs(off) <= HALF_STEP_RAD else heading_rad


def rigid_limit(twist: Twist2D, slots: Sequence[Vec2], v_max_mps: float) -> Twist2D:
    """`twist` scaled down (curvature kept) until every slot of a rigid shape moving with
    it needs at most `RIGID_SPEED_SHARE` of `v_max_mps` (slots in the leader's frame).
    """
    need = max(
        (
            math.hypot(twist.v_mps - twist.omega_radps * s.y_m, twist.omega_radps * s.x_m)
            for s in slots
        ),
        default=0.0,
    )
    allowed = RIGID_SPEED_SHARE * v_max_mps
    if need <= allowed:
        return twist
    scale = allowed / need
    return Twist2D(twist.v_mps * scale, twist.omega_radps * scale)


def turn_rate_radps(slots: Sequence[Vec2], v_max_mps: float, omega_max_radps: float) -> float:
    """The fastest turn on the spot that keeps every slot within its speed share."""
    reach_m = max((s.norm() for s in slots), default=0.0)
    if reach_m <= 0.0:
        return omega_max_radps
    return min(omega_max_radps, RIGID_SPEED_SHARE * v_max_mps / reach_m)


class WanderHeading:
    """A heading that changes every `wander_period_s` by up to `wander_turn_deg`, drawn
    from a seeded generator: the same on every run of a scenario.
    """

    def __init__(self, nav: NavigationConfig, seed: int) -> None:
        self.period_s = nav.wander_period_s
        self.turn_rad = math.radians(nav.wander_turn_deg)
        self._rng = np.random.default_rng(seed)
        self.heading_rad: float | None = None
        self._next_s = 0.0

    def heading(self, pose: Pose2D, t_s: float) -> float:
        """The world-frame heading to wander along at `t_s`."""
        if self.heading_rad is None:
            self.heading_rad = pose.theta_rad
        if t_s >= self._next_s:
            self._next_s = t_s + self.period_s
            turn = float(self._rng.uniform(-self.turn_rad, self.turn_rad))
            self.heading_rad = wrap_angle(self.heading_rad + turn)
        return self.heading_rad
