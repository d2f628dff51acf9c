"""Where a batch step's time goes, phase by phase, at a given fleet size.

`bench_vs_irsim.py`'s phalanx side (the paper scenario's grid of N robots among the same
circles), stepped by `BatchRunner` with a timer around each phase of a step: the world's
sonar cast (`World.statuses`), reading every ring as geometry (`read_all`), hearing each
robot (`Agent.hear`), masking the formation out of every reading (`mask_readings`), the
agents' steps (`Agent.step`), recording, and the world's integration (`World.step`).
The timers cost a little (the phases' sum against the untimed loop is printed).
Every time is also a ratio to the calibration workload timed in the same run
(`bench/calibration.py`).

    .venv/bin/python bench/bench_phases.py [--robots 3 10 100] [--steps 1000]
"""

from __future__ import annotations

import argparse
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from bench_vs_irsim import phalanx_scenario
from calibration import Calibration, load

import phalanx.runtime.batch as batch_module
from phalanx.agents.perception import SonarGeometry
from phalanx.runtime.batch import BatchRunner


def runner_for(n: int, steps: int) -> BatchRunner:
    """`bench_vs_irsim.py`'s phalanx run of `n` robots, `steps` steps long."""
    return BatchRunner(phalanx_scenario(n, steps))


def timed(spent: Counter[str], label: str, work: Callable[..., Any]) -> Callable[..., Any]:
    """`work`, adding its wall time to `spent[label]` on every call."""

    def call(*args: Any, **kwargs: Any) -> Any:
        started = time.perf_counter()
        try:
            return work(*args, **kwargs)
        finally:
            spent[label] += time.perf_counter() - started

    return call


def phases(n: int, steps: int) -> tuple[float, float, Counter[str]]:
    """The untimed loop's wall time, the timed loop's, and each phase's (s)."""
    plain = runner_for(n, steps)
    started = time.perf_counter()
    plain.run()
    untimed = time.perf_counter() - started
    runner, spent = runner_for(n, steps), Counter[str]()
    world = runner.world
    world.statuses = timed(spent, "cast", world.statuses)  # type: ignore[method-assign]
    world.step = timed(spent, "integrate", world.step)  # type: ignore[method-assign]
    for agent in runner.agents.values():
        agent.hear = timed(spent, "hear", agent.hear)  # type: ignore[method-assign]
        agent.step = timed(spent, "agents", agent.step)  # type: ignore[method-assign]
    runner._record = timed(spent, "record", runner._record)  # type: ignore[method-assign]
    read_all, mask = SonarGeometry.read_all, batch_module.mask_readings
    SonarGeometry.read_all = timed(spent, "read", read_all)  # type: ignore[method-assign]
    batch_module.mask_readings = timed(spent, "mask", mask)
    try:
        started = time.perf_counter()
        runner.run()
        whole = time.perf_counter() - started
    finally:
        SonarGeometry.read_all, batch_module.mask_readings = read_all, mask  # type: ignore[method-assign]
    return untimed, whole, spent


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--robots", type=int, nargs="+", default=[3, 10, 100])
    parser.add_argument("--steps", type=int, default=1000)
    args = parser.parse_args()
    cal = Calibration.measure()
    names = ("cast", "read", "hear", "mask", "agents", "record", "integrate")
    print("µs per step (milli-cal), each phase of a batch step")
    print(f"robots  {'  '.join(f'{k:>15s}' for k in names)}  timed / untimed loop  load")
    for n in args.robots:
        untimed, whole, spent = phases(n, args.steps)
        cells = "  ".join(
            f"{1e6 * spent[k] / args.steps:7.0f} ({1e3 * cal.ratio(spent[k] / args.steps):5.1f})"
            for k in names
        )
        print(f"{n:6d}  {cells}  {whole:5.2f} s / {untimed:5.2f} s  {load()}", flush=True)
    Calibration.measure()


if __name__ == "__main__":
    main()
