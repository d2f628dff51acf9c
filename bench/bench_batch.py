"""In-process batch runner speed: the paper scenario, and how it scales with robots.

Prints wall time and real-time factor of `run_batch` for the 200 s paper wedge run and
for grid formations (a multi-leader tree) of 3, 10, 100 and 1000 robots.

    .venv/bin/python bench/bench_batch.py [--max-robots 1000]
"""

from __future__ import annotations

import argparse
import time

from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.core.scenarios import grid_scenario
from phalanx.runtime.batch import run_batch


def timed(scenario):  # type: ignore[no-untyped-def]
    started = time.perf_counter()
    log = run_batch(scenario)
    wall = time.perf_counter() - started
    return wall, log


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--max-robots", type=int, default=1000)
    args = parser.parse_args()
    base = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
    wall, _ = timed(base)
    print(
        f"paper wedge, 3 robots, {base.duration_s:.0f} s sim: wall {wall:.2f} s, "
        f"{base.duration_s / wall:.0f}x real time"
    )
    print("robots  sim_s  wall_s  realtime_x  robot_steps_per_s  us_per_robot_step")
    for n in (3, 10, 100, 1000):
        if n > args.max_robots:
            break
        duration = 200.0 if n <= 100 else 20.0
        scenario = grid_scenario(base, n, duration_s=duration)
        wall, _ = timed(scenario)
        steps = n * duration * scenario.control_rate_hz
        print(
            f"{n:6d}  {duration:5.0f}  {wall:6.2f}  {duration / wall:10.1f}  "
            f"{steps / wall:17.0f}  {1e6 * wall / steps:17.1f}"
        )


if __name__ == "__main__":
    main()
