"""What one robot remembers from step to step, besides its behaviours' own state.

Each piece is small and named for what it holds; the agent (`phalanx.agents.agent`)
updates them in the estimate stage of a step, before the state machine decides, and
the behaviours that need one are given it when they are made. What the navigator
remembers (its steering, the leader's course, the stall watch) is navigation's
(`phalanx.agents.navigation`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from phalanx.agents.leadership import FlagsView, LiveFlags


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
class Route:
    """The leader's waypoints (world frame, m): the scenario's, or, once an operator gave
    it a goal, the waypoints reached before it and the goal in place of the rest.
    """

    waypoints: tuple[tuple[float, float], ...]

    def replace_rest(self, reached: int, goal: tuple[float, float]) -> None:
        """`goal` in place of every waypoint from index `reached` on."""
        self.waypoints = (*self.waypoints[:reached], goal)


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
        if not live.stopped:  # (what follows, when nobody is stopped)
            self.cut_by = self.before = frozenset()
            return
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
        return bool(live.stopped) and bool(live.stopped - {own_id} - self.before)
