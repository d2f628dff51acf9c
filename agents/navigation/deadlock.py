"""Getting a navigating group out of a dead end (the paper's section 3.2, and ours): the
sign that a leader is stuck though nothing stands right ahead (`StallWatch`), the way
back out, straight back or along the arc just driven (`reverse_twist`) or along the path
it came (`Breadcrumbs.back_along`), the heading to turn to after (`free_heading_near`),
and the leader's way so far (`Course`: that path, and a point to make for first once it
has turned).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from phalanx.agents.navigation.clearance import (
    HEADINGS_RAD,
    clearance_along,
    corridor_clearance,
    heading_offsets_rad,
)
from phalanx.agents.perception import FloatArray
from phalanx.core.config import DeadlockConfig
from phalanx.core.geometry import Pose2D, Twist2D, Vec2

# The deadlock reverse never retraces a tighter arc than this (a crawl's curvature is noise).
RETRACE_MIN_RADIUS_M = 2.0
# A navigating leader that has not got this far from where it was in `stall_s` is stuck.
PROGRESS_M = 0.3


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

    def came_by(self, point: Vec2, *, within_m: float, skip_m: float) -> bool | None:
        """Whether `point` lies within `within_m` of the path, leaving out its last
        `skip_m` (the ground the robot stands on); None when the path is no longer.
        """
        points = self._points
        along_m, longer = 0.0, False
        for k in range(len(points) - 1, 0, -1):
            along_m += (points[k] - points[k - 1]).norm()
            if along_m < skip_m:
                continue
            longer = True
            if (points[k - 1] - point).norm() <= within_m:
                return True
        return False if longer else None

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


@dataclass
class Course:
    """The leader's way so far: the ground it crossed (to back along) and a point to make
    for first after a dead end (world frame).
    """

    crumbs: Breadcrumbs
    escape: Vec2 | None = None


class StallWatch:
    """Whether a navigating leader that turns and creeps gets anywhere: one that has not
    moved `PROGRESS_M` from where it was for `stall_s` is blocked as surely as one
    facing a wall.
    """

    def __init__(self, stall_s: float) -> None:
        self.stall_s = stall_s
        self._anchor: tuple[Vec2, float] | None = None  # where and when progress was made

    def stalled(self, pose: Pose2D, t_s: float) -> bool:
        """Update with the pose at `t_s`; whether the robot is stalled."""
        here = pose.position
        if self._anchor is None or (here - self._anchor[0]).norm() >= PROGRESS_M:
            self._anchor = (here, t_s)
        return t_s - self._anchor[1] >= self.stall_s

    def reset(self) -> None:
        """Start watching afresh (a new behaviour, or not navigating)."""
        self._anchor = None


def free_heading_near(
    points: tuple[FloatArray, FloatArray], heading_rad: float, *, half_width_m: float, room_m: float
) -> float:
    """The heading (body frame) to turn to for `heading_rad`: itself if the robot's own
    corridor along it is free for `room_m`, else the candidate heading nearest it that
    is (a turn back onto a way the robot stands blocked on would only meet the same
    deadlock again); `heading_rad` if none is.
    """
    if clearance_along(points, heading_rad, half_width_m=half_width_m) >= room_m:
        return heading_rad
    free = corridor_clearance(points, HEADINGS_RAD, half_width_m=half_width_m) >= room_m
    if not free.any():
        return heading_rad
    off = np.where(free, heading_offsets_rad(heading_rad), np.inf)
    return float(HEADINGS_RAD[int(np.argmin(off))])
