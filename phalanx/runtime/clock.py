"""When an agent steps: its clock. A simulated robot steps on the world's ticks (each
sense frame is one, see `phalanx.runtime.robot_io.WorldLink`); a robot on a driver
keeps its own clock, step k at `epoch + k * dt` on the wall clock (Unix time: every
agent and the world of a fleet are given the same epoch, so their scenario times agree
within the hosts' clock sync).
"""

from __future__ import annotations

import math
import time
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
