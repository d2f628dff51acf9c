"""Choosing a heading round obstacles, and the twist that takes it: the heading nearest
the one wanted whose corridor is free (`choose_heading`), turned towards and driven at a
speed that falls as the way ahead tightens (`steer`), nudged away from the nearer side
wall (`centring_rad`), slowed so that every slot of a rigid shape keeps up
(`rigid_limit`, `turn_rate_radps`); and what the navigator remembers from step to step
(`Steering`, `RecentEchoes`).

Every function turns what the robot knows into an unsaturated twist; the limiter comes
after, as for the formation controllers.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from phalanx.agents.navigation.clearance import HEADINGS_RAD, Clearances
from phalanx.agents.perception import FloatArray
from phalanx.core.config import NavigationConfig
from phalanx.core.geometry import Pose2D, Twist2D, Vec2, wrap_angle

# Free way enough to head straight for where one wants to go (m).
NEAR_NEED_M = 2.0
# Weight of "close to the last choice" against "close to the goal" (choose_heading).
STICKINESS = 0.5
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


def choose_heading(
    desired_rad: float,
    *,
    wide: FloatArray,
    narrow: FloatArray,
    need_m: float,
    window_rad: float = math.pi,
    previous_rad: float | None = None,
    reach_rad: float = math.pi,
    headings_rad: FloatArray = HEADINGS_RAD,
) -> int:
    """Index of the heading to take, among those within `window_rad` of `desired_rad`:
    the one nearest `desired_rad` whose whole-formation corridor (`wide`) is free for
    `need_m`; else whose own corridor (`narrow`) is; else straight for the goal. Ties
    go to the smaller turn, then to the left. With `previous_rad` (the last choice), a
    heading near it costs less: a navigator facing an obstacle head-on picks a side and
    keeps to it instead of dithering between two equally good ways round.

    The window keeps a navigator from turning its back on the goal: what cannot be got
    round within it is a dead end, the deadlock escape's business. `reach_rad` also
    keeps the choice within that much of straight ahead (a shape with no room to turn
    on the spot can only bend its course).
    """
    off = _angle_between(headings_rad, desired_rad)
    inside = (off <= window_rad + 1e-9) & (np.abs(headings_rad) <= reach_rad + 1e-9)
    if not inside.any():
        inside = off <= off.min() + 1e-9
    turn = np.abs(headings_rad)
    # Going the desired way needs only room to make progress; turning away from it
    # needs the full `need_m`, or a narrow opening towards the goal would lose to any
    # wide-open side.
    need = np.minimum(need_m, NEAR_NEED_M + (need_m - NEAR_NEED_M) * off / max(window_rad, 1e-9))
    if previous_rad is not None:
        off = off + STICKINESS * _angle_between(headings_rad, previous_rad)
    for free in (inside & (wide >= need), inside & (narrow >= need)):
        if free.any():
            return _first(np.lexsort((-headings_rad, turn, np.where(free, off, np.inf))))
    # No way round within the window: keep heading for the goal and let the robot creep
    # up to the obstacle, where being blocked hands the problem to the group's rules
    # (handover, deadlock) instead of turning the formation about in a tight spot.
    return _first(np.lexsort((-headings_rad, off)))


def _angle_between(headings_rad: FloatArray, angle_rad: float) -> FloatArray:
    return np.abs(np.mod(headings_rad - angle_rad + math.pi, 2.0 * math.pi) - math.pi)


def _first(order: npt.NDArray[np.intp]) -> int:
    return int(order[0])


def bearing_rad(pose: Pose2D, point: Vec2) -> float:
    """Direction of `point` from `pose`, in the body frame (rad, counter-clockwise)."""
    local = pose.to_body(point)
    return math.atan2(local.y_m, local.x_m)


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


@dataclass
class Steering:
    """The reactive navigator's memory (world frame, rad): the heading it last steered
    for, and a turn on the spot under way. NAVIGATE, WANDER and AVOID share it (a
    follower that takes the lead keeps the side it was going round by).
    """

    chosen_rad: float | None = None
    turn_to_rad: float | None = None

    def reset(self) -> None:
        """Forget both (a robot that stopped steering)."""
        self.chosen_rad = None
        self.turn_to_rad = None


class RecentEchoes:
    """The obstacle points a navigator's sonar showed over the last `keep_s` (world
    frame), to steer by. A ring of beams loses and finds an obstacle between two beams
    as the robot yaws; steering by one step's echoes alone then swings from side to side,
    and the shape behind swings with it.
    """

    def __init__(self, keep_s: float) -> None:
        self.keep_s = keep_s
        self._steps: deque[tuple[float, FloatArray, FloatArray]] = deque()

    def with_recent(
        self, pose: Pose2D, points: tuple[FloatArray, FloatArray], t_s: float
    ) -> tuple[FloatArray, FloatArray]:
        """Remember this step's `points` (body frame, at `pose`); this step's and the
        last `keep_s`'s, in the body frame.
        """
        c, s = math.cos(pose.theta_rad), math.sin(pose.theta_rad)
        x, y = points
        steps = self._steps
        steps.append((t_s, pose.x_m + c * x - s * y, pose.y_m + s * x + c * y))
        while steps[0][0] < t_s - self.keep_s - 1e-9:
            steps.popleft()
        if len(steps) == 1:
            return points
        dx = np.concatenate([p[1] for p in steps]) - pose.x_m
        dy = np.concatenate([p[2] for p in steps]) - pose.y_m
        return c * dx + s * dy, c * dy - s * dx
