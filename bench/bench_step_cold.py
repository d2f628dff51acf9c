"""The agent core's step after a pause: what a 20 Hz follower pays for waking up.

`bench_zenoh_latency.py`'s latency is the hop (leader's state put -> follower's
process) plus the follower's step, run once per state, 50 ms apart. This steps the same
follower (`g1` of a 10-robot grid, the benchmark's inputs) in one process, with
nothing between two steps, 5, 20 or 50 ms of busy waiting, or 50 ms asleep (also with
the garbage collector frozen after warm-up); its sonar reading open space, or its
formation's robots (`bench_zenoh_latency.sonar_ranges`).
Each row: p50 / p90 / p99 of the step's wall time, and p99 as a ratio to the
calibration workload timed in the same run (`bench/calibration.py`).

    .venv/bin/python bench/bench_step_cold.py [--steps 300] [--sonar open formation]
"""

from __future__ import annotations

import argparse
import gc
import itertools
import statistics
import time
from collections.abc import Callable

from bench_zenoh_latency import driving, fleet_scenario, sonar_ranges
from calibration import Calibration, load

from phalanx.agents.agent import Agent, Observation
from phalanx.core.config_files import load_robot
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.robot import Odometry, RobotStatus

PAUSE_S = 0.05  # a 20 Hz leader's states, one step each
WARMUP = 50


def follower(sonar: str = "open") -> Callable[[int], float]:
    """One step of the benchmark's follower on its leader's state `seq`: its wall time;
    `sonar`: what it reads (`sonar_ranges`).
    """
    scenario = fleet_scenario(10)
    formation = scenario_formation(scenario)
    rid = "g1"
    agent = Agent(rid, scenario=scenario, robot=load_robot("p3dx"), formation=formation)
    leader_id = formation.leader_of(rid)
    if leader_id is None:
        raise SystemExit(f"{rid} has no leader in the grid")
    here, there = formation.positions[rid], formation.positions[leader_id]
    status = RobotStatus(sonar_ranges_m=sonar_ranges(10, sonar)[rid])

    def step(seq: int) -> float:
        now = time.monotonic()
        lead = driving(leader_id, there, seq, now)
        odometry = Odometry(Pose2D(here.x_m, here.y_m, 0.0), Twist2D(0.15, 0.0), now)
        started = time.perf_counter()
        agent.step(Observation(odometry, status), {leader_id: lead.peer()}, now)
        return time.perf_counter() - started

    return step


# What lies between two steps: (label, busy waiting?, seconds, garbage collector frozen?)
PAUSES = (
    ("nothing", True, 0.0, False),
    ("busy 5 ms", True, 0.005, False),
    ("busy 20 ms", True, 0.02, False),
    ("busy 50 ms", True, PAUSE_S, False),
    ("asleep 50 ms", False, PAUSE_S, False),
    ("asleep, gc frozen", False, PAUSE_S, True),
)


def pause(busy: bool, seconds: float) -> None:
    """Between two steps: `seconds` of busy waiting, or asleep."""
    if not busy:
        time.sleep(seconds)
        return
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument(
        "--sonar", nargs="+", default=["open", "formation"], choices=["open", "formation"]
    )
    args = parser.parse_args()
    cal = Calibration.measure()
    print("the follower's step after a pause (ms)")
    print("sonar      between steps       p50     p90     p99  p99_mcal  load")
    for sonar, (label, busy, seconds, frozen) in itertools.product(args.sonar, PAUSES):
        step = follower(sonar)
        for k in range(WARMUP):
            step(k)
        if frozen:
            gc.freeze()
        times = []
        for k in range(WARMUP, WARMUP + args.steps):
            pause(busy, seconds)
            times.append(step(k))
        gc.unfreeze()
        q = statistics.quantiles(times, n=100)
        print(
            f"{sonar:9s}  {label:17s}  {1e3 * q[49]:6.3f}  {1e3 * q[89]:6.3f}  {1e3 * q[98]:6.3f}  "
            f"{1e3 * cal.ratio(q[98]):8.1f}  {load()}",
            flush=True,
        )
    Calibration.measure()


if __name__ == "__main__":
    main()
