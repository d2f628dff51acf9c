"""What one robot remembers from step to step, besides its behaviours' own state.

Each piece is small and named for what it holds; the agent (`phalanx.agents.agent`)
updates them in the estimate stage of a step, before the state machine decides, and
the behaviours that need one are given it when they are made.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from phalanx.agents.behaviours.navigation import Breadcrumbs
from phalanx.agents.leadership import FlagsView, LiveFlags
from phalanx.agents.perception import FloatArray
from phalanx.core.geometry import Pose2D, Vec2

# A navigating leader that has not got this far from where it was in `stall_s` is stuck.
PROGRESS_M = 0.3


@dataclass
class Progress:
    """The group's progress: the next waypoint, the deadlocks at it and the scripted
    profile's clock (s). The leader keeps it; followers copy it from the leader's flags,
    so whoever leads next carries on from the same place.
    """

    waypoint: int = 0
    deadlocks: int = 0
    profile_s: float = 0.0

    def copy_from(self, leader: FlagsView) -> None:
        """Take the leader's progress as it published it."""
        self.waypoint, self.deadlocks, self.profile_s = (
            leader.waypoint,
            leader.deadlocks,
            leader.profile_s,
        )


@dataclass
class BlockedTimers:
    """How long the path each way has been blocked (s): forwards (+1), backwards (-1)."""

    seconds: dict[int, float] = field(default_factory=lambda: {1: 0.0, -1: 0.0})

    def update(self, blocked: dict[int, bool], dt_s: float) -> None:
        """One step more of each way's blocked time (reset where it is free)."""
        for way, now in blocked.items():
            self.seconds[way] = self.seconds[way] + dt_s if now else 0.0

    def of(self, direction: int) -> float:
        """How long the way `direction` (+1 or -1) has been blocked."""
        return self.seconds[direction]

    def reset(self) -> None:
        """A new heading: blocked only if blocked again."""
        self.seconds = {1: 0.0, -1: 0.0}


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


@dataclass
class Course:
    """The leader's way so far: the ground it crossed (to back along) and a point to make
    for first after a dead end (world frame).
    """

    crumbs: Breadcrumbs
    escape: Vec2 | None = None


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


@dataclass
class StartUp:
    """When the agent's first step was, and until when robots not heard yet count as in
    their slots (the scenario's start).
    """

    started_s: float | None = None
    assume_formed_until_s: float = -math.inf

    def begin(self, t_s: float, grace_s: float) -> None:
        """Record the first step (only the first call counts)."""
        if self.started_s is None:
            self.started_s = t_s
            self.assume_formed_until_s = t_s + grace_s

    def waited_s(self, t_s: float) -> float:
        """How long since the first step."""
        return t_s - (self.started_s if self.started_s is not None else t_s)


@dataclass
class StopsBefore:
    """The robots in an emergency stop that the deadlock reverse passes over (a leader's).

    Robots already stopped as the reverse begins stopped for what lay ahead, which the
    reverse moves away from: not a reason to end it (until one moves, and stops again
    during the reverse). One that stopped backing up is (the
    reverse would drive the group at what stopped it), once per stop: still stopped at the
    next deadlock, it is passed over and the group backs away regardless, else a group
    boxed in would start and end reverses on the spot, for ever.
    """

    before: frozenset[str] = frozenset()
    cut_by: frozenset[str] = frozenset()  # stopped backing up, have cut a reverse short

    def update(self, live: LiveFlags, own_id: str, *, reversing: bool) -> None:
        """Every step: forget a robot that moved again; outside the reverse, take who is
        stopped now (and may be passed over, should a reverse begin).
        """
        self.cut_by &= live.stopped_behind
        if not reversing:
            self.before = live.stopped - (live.stopped_behind - self.cut_by) - {own_id}
        else:
            self.before &= live.stopped  # one that moved again and stops anew ends it

    def reverse_begins(self, live: LiveFlags) -> None:
        """The reverse begins: those stopped backing up have had their cut."""
        self.cut_by |= live.stopped_behind

    def someone_stopped(self, live: LiveFlags, own_id: str) -> bool:
        """Whether a robot is stopped that the reverse does not pass over."""
        return bool(live.stopped - {own_id} - self.before)
