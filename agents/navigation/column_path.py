"""The path a robot drove, for a column: a follower whose slot is straight behind the
robot it is laid out from (the leader, or the robot it tracks while the leader is not
heard) keeps to that robot's path, its slot the slot's distance back along it, instead
of to a slot held rigidly behind, which swings out with every turn.

A rigid slot 1 m behind a robot turning on a 0.5 m radius lies 0.6 m outside its arc,
one 4 m behind 3.5 m outside: a column's tail sweeps across what the robots ahead of it
went round. The path they drove is free of it. On a straight course both are one point.
"""

from __future__ import annotations

import math
from bisect import bisect_left

from phalanx.core.geometry import Pose2D, Vec2

# Points are kept this far apart along the path (m), and as many as cover this length.
SPACING_M = 0.05
KEPT_M = 12.0
# The slot's heading: the path's direction over this much of it, centred on the slot (m).
HEADING_CHORD_M = 0.1
# The robot heard this far from the path's last point (a gap in what was heard) starts a
# new path (m).
JUMP_M = 0.5
# The robot drives backwards faster than this: the path behind it is being driven over
# again, and the group is reversing (m/s).
REVERSE_MPS = 0.02


class Trail:
    """The positions the robot was heard at, oldest first, `SPACING_M` apart, with
    the length of path up to each (m; a look-up back along it is a bisection).
    """

    def __init__(self) -> None:
        self.robot_id: str | None = None
        self._keep = math.ceil(KEPT_M / SPACING_M) + 2
        self._xs: list[float] = []
        self._ys: list[float] = []
        self._along: list[float] = []

    def __len__(self) -> int:
        return len(self._xs)

    def clear(self) -> None:
        """Forget the path."""
        self._xs.clear()
        self._ys.clear()
        self._along.clear()

    def hear(self, robot_id: str, position: Vec2, v_mps: float) -> None:
        """The robot `robot_id` is at `position`, driving at `v_mps` (another robot, or
        this one driving backwards or heard far from where it was, starts a new path).
        """
        xs, ys, along = self._xs, self._ys, self._along
        step_m = math.hypot(position.x_m - xs[-1], position.y_m - ys[-1]) if xs else 0.0
        if robot_id != self.robot_id or v_mps < -REVERSE_MPS or step_m > JUMP_M:
            self.clear()
            self.robot_id = robot_id
        if not xs:
            xs.append(position.x_m)
            ys.append(position.y_m)
            along.append(0.0)
        elif step_m >= SPACING_M:
            xs.append(position.x_m)
            ys.append(position.y_m)
            along.append(along[-1] + step_m)
            if len(xs) > 2 * self._keep:  # (dropped in batches: amortised O(1))
                del xs[: -self._keep], ys[: -self._keep], along[: -self._keep]

    def point_back(self, position: Vec2, distance_m: float) -> Vec2 | None:
        """The point `distance_m` back along the path from `position` (the robot now),
        or None if the path is shorter.
        """
        xs, ys, along = self._xs, self._ys, self._along
        if not xs:
            return None
        x, y = position.x_m, position.y_m
        tail_m = math.hypot(x - xs[-1], y - ys[-1])
        if distance_m <= tail_m:  # between the last point heard and now
            share = distance_m / tail_m if tail_m > 0.0 else 0.0
            return Vec2(x + (xs[-1] - x) * share, y + (ys[-1] - y) * share)
        at_m = along[-1] - (distance_m - tail_m)
        if at_m < along[0]:
            return None
        i = max(1, bisect_left(along, at_m))
        share = (along[i] - at_m) / (along[i] - along[i - 1])
        return Vec2(xs[i] + (xs[i - 1] - xs[i]) * share, ys[i] + (ys[i - 1] - ys[i]) * share)

    def pose_back(self, position: Vec2, distance_m: float) -> Pose2D | None:
        """The pose `distance_m` back along the path from `position`, heading along the
        path (the direction it was driven in, over a chord centred on the point), or
        None if the path is shorter.
        """
        half_m = HEADING_CHORD_M / 2
        here = self.point_back(position, distance_m)
        behind = self.point_back(position, distance_m + half_m) or here
        ahead = self.point_back(position, max(0.0, distance_m - half_m))
        if here is None or behind is None or ahead is None:
            return None
        heading_rad = math.atan2(ahead.y_m - behind.y_m, ahead.x_m - behind.x_m)
        return Pose2D(here.x_m, here.y_m, heading_rad)
