"""When an agent steps: its clock. A simulated robot steps on the world's ticks (each
sense frame is one, see `phalanx.runtime.robot_io.WorldLink`); a robot on a driver
keeps its own clock, step k at `epoch + k * dt` on the wall clock (Unix time: every
agent and the world of a fleet are given the same epoch, so their scenario times agree
within the hosts' clock sync).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from phalanx.runtime.signals import Stoppable

# A clock started this share of a period past a step still takes that step.
FIRST_STEP_GRACE = 0.5


@dataclass(frozen=True, slots=True)
class Tick:
    """Control step `k` at fleet time `t_s` (s since the run's start)."""

    k: int
    t_s: float


class Clock(Protocol):
    """Hands out control steps, in order, until the run is over."""

    def next_tick(self, stop: Stoppable) -> Tick | None:
        """Block until the next control instant; None once the run is over (or `stop`)."""
        ...


class EpochClock:
    """Step k at `epoch_s + k * dt_s` (Unix time), for `steps` steps. A step that cannot
    be served in time is skipped rather than bunched up (counted in `overruns`).
    """

    def __init__(self, *, epoch_s: float, dt_s: float, steps: int) -> None:
        self.epoch_s, self.dt_s, self.steps = epoch_s, dt_s, steps
        self.overruns = 0
        self._k: int | None = None

    def next_tick(self, stop: Stoppable) -> Tick | None:
        """The next step on the wall clock."""
        if self._k is None:
            if self.epoch_s > time.time() and stop.wait(self.epoch_s - time.time()):
                return None
            # (a process that woke at the epoch is a hair past it: that is step 0, not a
            # step to skip; one started later joins at the next step to come)
            late = (time.time() - self.epoch_s) / self.dt_s
            self._k = max(0, math.ceil(late - FIRST_STEP_GRACE))
        k = self._k
        if k >= self.steps or stop.is_set():
            return None
        wait_s = self.epoch_s + k * self.dt_s - time.time()
        if wait_s > 0 and stop.wait(wait_s):
            return None
        late_ticks = math.floor((time.time() - self.epoch_s) / self.dt_s) - k
        if late_ticks > 0:  # skip what cannot be done in time rather than bunch up
            self.overruns += 1
            k += late_ticks
        self._k = k + 1
        return Tick(k, k * self.dt_s)


class WorldSchedule:
    """When a real-time world runs its ticks: every `period_s` from its first (`start`),
    or, given the run's epoch (Unix time of tick 0, shared with the robots on drivers), on
    that epoch's grid, where the robots' steps and the world's motion-capture fixes are.

    A tick whose work outlasted the period is an overrun. Without an epoch the next tick
    comes a period after the late one (a world's own pace, never a burst); with one, the
    late ticks run back to back until the world is on the grid again: a world that kept
    its delay would describe its robots as they were that long ago, to emulated robots
    reporting to agents on the epoch's clock.
    """

    def __init__(
        self,
        period_s: float,
        epoch_s: float | None = None,
        *,
        now: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
    ) -> None:
        self.period_s, self.epoch_s = period_s, epoch_s
        self.now, self.wall = now, wall
        self.overruns = 0
        self._next_s = now()

    def start(self) -> None:
        """Tick 0 is now, or at the epoch if there is one (a wake-up's delay after it
        does not shift the grid).
        """
        self._next_s = self.now()
        if self.epoch_s is not None:
            self._next_s -= max(0.0, self.wall() - self.epoch_s)

    def wait_s(self) -> float:
        """After a tick: how long until the next one is due (0: at once)."""
        self._next_s += self.period_s
        slack_s = self._next_s - self.now()
        if slack_s < 0.0:
            self.overruns += 1
            if self.epoch_s is None:
                self._next_s = self.now()
        return max(0.0, slack_s)
