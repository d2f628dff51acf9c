"""A run's loop steps with what existed before it frozen for the garbage collector
(`phalanx.runtime.heap.lifelong_heap`), in one process and in an agent process, and
lets it go when the loop is over.
"""

from __future__ import annotations

import gc
import time

from agentlab import agent_on_driver
from fleetlab import wait_for

from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_robot, load_scenario
from phalanx.core.limits import safety_limits
from phalanx.drivers.canopen import CanopenDriver, CanopenSettings
from phalanx.drivers.safety import SafeDriver
from phalanx.runtime.batch import BatchRunner
from phalanx.runtime.clock import EpochClock, Tick
from phalanx.runtime.heap import lifelong_heap
from phalanx.runtime.robot_io import DriverIO
from phalanx.runtime.signals import Stoppable
from phalanx.simulator.cia402 import SimulatedDiffDrive

ROBOT = load_robot("p3dx")
WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"


def test_the_heap_is_frozen_inside_and_let_go_after_any_loop_ends() -> None:
    assert gc.get_freeze_count() == 0
    with lifelong_heap():
        assert gc.get_freeze_count() > 0
        with lifelong_heap():  # (another loop of the process, in a thread)
            assert gc.get_freeze_count() > 0
        assert gc.get_freeze_count() == 0, "what a finished loop leaves must be collectable"
    assert gc.get_freeze_count() == 0


def test_the_heap_is_let_go_when_a_loop_fails() -> None:
    try:
        with lifelong_heap():
            raise RuntimeError("a loop that fails")
    except RuntimeError:
        pass
    assert gc.get_freeze_count() == 0


def test_a_batch_run_steps_with_the_heap_frozen() -> None:
    scenario = apply_overrides(load_scenario(WEDGE), ["duration_s=1"])
    counts: list[int] = []

    def record(_runner: BatchRunner) -> bool:
        counts.append(gc.get_freeze_count())
        return False

    BatchRunner(scenario).run(until=record)
    assert len(counts) == round(1.0 / scenario.dt_s)
    assert min(counts) > 0
    assert gc.get_freeze_count() == 0


class _Watched(EpochClock):
    """An epoch clock that notes, at each tick it hands out, how many objects are frozen."""

    def __init__(self, *, epoch_s: float, dt_s: float, steps: int) -> None:
        super().__init__(epoch_s=epoch_s, dt_s=dt_s, steps=steps)
        self.frozen: list[int] = []

    def next_tick(self, stop: Stoppable) -> Tick | None:
        tick = super().next_tick(stop)
        self.frozen.append(gc.get_freeze_count())
        return tick


def test_an_agent_runtime_steps_with_the_heap_frozen() -> None:
    """The agent over the safety wrapper and a CiA 402 drive on python-can's virtual bus."""
    scenario = apply_overrides(load_scenario(WEDGE), ["duration_s=30"])
    channel = "heap-agent-runtime"
    with SimulatedDiffDrive(channel):
        driver = CanopenDriver(CanopenSettings(interface="virtual", channel=channel), robot=ROBOT)
        with SafeDriver(driver, safety_limits(ROBOT, scenario.limits)) as safe:
            clock = _Watched(epoch_s=time.time() + 0.3, dt_s=scenario.dt_s, steps=300)
            io = DriverIO(safe, ROBOT, origin=scenario.start_pose("r1"))
            with agent_on_driver(scenario, ROBOT, io, clock, fleet="heap") as runtime:
                assert wait_for(lambda: runtime.steps >= 5, 20.0, poll_s=0.005)
    assert len(clock.frozen) >= 5
    assert min(clock.frozen) > 0
    assert gc.get_freeze_count() == 0
