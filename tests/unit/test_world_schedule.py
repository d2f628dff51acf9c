"""A real-time world's ticks on the wall clock: on the run's epoch's grid when it has one
(late ticks run back to back until it is on it again), else at its own pace."""

from __future__ import annotations

import pytest

from phalanx.runtime.clock import WorldSchedule

EPOCH_S = 1_000_000.0  # Unix time of tick 0


class Clocks:
    """A monotonic and a wall clock the test moves together by hand."""

    def __init__(self, wall_s: float) -> None:
        self.wall_s = wall_s

    def now(self) -> float:
        return self.wall_s - 999_000.0  # (any offset: a monotonic clock's zero is its own)

    def wall(self) -> float:
        return self.wall_s


def _ticks(schedule: WorldSchedule, clocks: Clocks, work_s: list[float]) -> list[float]:
    """Run ticks taking `work_s` each; the wall time each one started."""
    started = []
    schedule.start()
    for work in work_s:
        started.append(clocks.wall_s)
        clocks.wall_s += work
        clocks.wall_s += schedule.wait_s()
    return started


def test_with_an_epoch_the_world_gets_back_on_its_grid_after_a_late_tick() -> None:
    clocks = Clocks(EPOCH_S + 0.004)  # (woken a little after the epoch)
    schedule = WorldSchedule(0.1, EPOCH_S, now=clocks.now, wall=clocks.wall)
    started = _ticks(schedule, clocks, [0.01, 0.01, 0.35, 0.01, 0.01, 0.01, 0.01, 0.01])
    # tick 2 took 0.35 s: ticks 3-5 were due meanwhile and run at once; from tick 6 on
    # every tick starts at its own instant of the epoch's grid again
    assert started[3] == pytest.approx(EPOCH_S + 0.55)
    assert started[4] == pytest.approx(EPOCH_S + 0.56)
    assert started[6:] == pytest.approx([EPOCH_S + 0.6, EPOCH_S + 0.7])
    assert started[:3] == pytest.approx([EPOCH_S + 0.004, EPOCH_S + 0.1, EPOCH_S + 0.2])
    assert schedule.overruns == 3  # ticks 2, 3 and 4 ended past the next one's instant


def test_without_an_epoch_a_late_tick_shifts_the_world_and_never_bursts() -> None:
    clocks = Clocks(EPOCH_S)
    schedule = WorldSchedule(0.1, now=clocks.now, wall=clocks.wall)
    started = _ticks(schedule, clocks, [0.01, 0.35, 0.01, 0.01])
    assert started == pytest.approx([EPOCH_S, EPOCH_S + 0.1, EPOCH_S + 0.45, EPOCH_S + 0.55])
    assert schedule.overruns == 1


def test_a_world_started_past_its_epoch_runs_the_ticks_it_missed_at_once() -> None:
    clocks = Clocks(EPOCH_S + 0.25)  # (its robots took that long to come up)
    schedule = WorldSchedule(0.1, EPOCH_S, now=clocks.now, wall=clocks.wall)
    started = _ticks(schedule, clocks, [0.0] * 5)
    assert started == pytest.approx([EPOCH_S + 0.25] * 3 + [EPOCH_S + 0.3, EPOCH_S + 0.4])
