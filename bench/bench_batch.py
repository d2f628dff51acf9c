"""In-process batch runner speed: the paper scenario, and how it scales with robots.

Prints wall time and real-time factor of `run_batch` for the 200 s paper wedge run and
for grid formations (a multi-leader tree) of 3, 10, 100 and 1000 robots, each repeated
and reported as its median, with the machine's load beside it and every time as a
ratio to the calibration workload timed in the same run (`bench/calibration.py`).

    .venv/bin/python bench/bench_batch.py [--max-robots 1000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import time

from calibration import Calibration, load

from phalanx.core.config import Scenario
from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.core.scenarios import grid_scenario
from phalanx.runtime.batch import BatchRunner


def timed(scenario: Scenario) -> tuple[float, float]:
    """(building the runner, running it) in seconds."""
    started = time.perf_counter()
    runner = BatchRunner(scenario)
    built = time.perf_counter()
    runner.run()
    return built - started, time.perf_counter() - built


def median_run(scenario: Scenario, repeats: int) -> tuple[float, float, list[float]]:
    """Median build and run times, and every run time."""
    times = [timed(scenario) for _ in range(repeats)]
    runs = [t[1] for t in times]
    return statistics.median(t[0] for t in times), statistics.median(runs), runs


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--max-robots", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    cal = Calibration.measure()
    base = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
    _, wall, runs = median_run(base, max(args.repeats, 5))
    print(
        f"paper wedge, 3 robots, {base.duration_s:.0f} s sim: wall {wall:.2f} s "
        f"({cal.cal(wall)}), {base.duration_s / wall:.0f}x real time "
        f"(runs {', '.join(f'{r:.2f}' for r in runs)}; load {load()})"
    )
    print(
        "robots  sim_s  build_s  wall_s  wall_cal  realtime_x  robot_steps_per_s  "
        "us_per_robot_step  us_cal  load"
    )
    for n in (3, 10, 100, 1000):
        if n > args.max_robots:
            break
        duration = 200.0 if n <= 10 else 20.0 if n <= 100 else 5.0
        scenario = grid_scenario(base, n, duration_s=duration)
        build, wall, _ = median_run(scenario, args.repeats)
        steps = n * duration * scenario.control_rate_hz
        us = 1e6 * wall / steps
        print(
            f"{n:6d}  {duration:5.0f}  {build:7.2f}  {wall:6.2f}  {cal.ratio(wall):8.1f}  "
            f"{duration / wall:10.1f}  {steps / wall:17.0f}  {us:17.1f}  "
            f"{cal.ratio(us * 1e-6) * 1e3:6.2f}m  {load()}",
            flush=True,
        )
    Calibration.measure()


if __name__ == "__main__":
    main()
