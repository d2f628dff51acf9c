"""What a sweep's Dask workers cost its runs: the same runs (the `field` family's wedge of
three, the sweep's `run_job`) on two worker processes three ways, round after round, the
order turned every round so a change in the machine's speed falls on all three:

- `phalanx sweep`'s local cluster as it is (Dask's housekeeping made rarer, `QUIET_DASK`);
- the same cluster with Dask's own housekeeping settings;
- a plain process pool of as many processes (no Dask at all).

Printed per way and round: the runs' own time summed ("run time", as the sweep's rows
report it), the wall time, and the CPU time of the process that drives them (where
the scheduler and the nannies of a local cluster run, on the same cores); then each
way's run time over the pool's, round by round, and the median.

    .venv/bin/python bench/bench_sweep_workers.py [--runs 30] [--rounds 3] [--workers 2]
"""

from __future__ import annotations

import argparse
import resource
import statistics
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ProcessPoolExecutor
from typing import Any

from calibration import Calibration, load

from phalanx.analysis.sweep import QUIET_DASK, Job, local_cluster, run_job

Rows = list[dict[str, Any]]


def on_cluster(housekeeping: Mapping[str, Any]) -> Callable[[list[Job], int], Rows]:
    """The runs on a local cluster with these housekeeping settings."""

    def run(todo: list[Job], workers: int) -> Rows:
        from dask.distributed import Client, as_completed

        with local_cluster(workers, housekeeping) as cluster, Client(cluster) as client:
            futures = client.map(run_job, todo, pure=False)
            return [f.result() for f in as_completed(futures)]  # type: ignore[no-untyped-call]

    return run


def in_pool(todo: list[Job], workers: int) -> Rows:
    """The runs in a plain process pool."""
    with ProcessPoolExecutor(workers) as pool:
        return list(pool.map(run_job, todo))


WAYS: dict[str, Callable[[list[Job], int], Rows]] = {
    "sweep (QUIET_DASK)": on_cluster(QUIET_DASK),
    "Dask's own settings": on_cluster({}),
    "process pool": in_pool,
}


def _cpu_s() -> float:
    used = resource.getrusage(resource.RUSAGE_SELF)
    return used.ru_utime + used.ru_stime


def measure(way: str, todo: list[Job], workers: int) -> tuple[float, float, float]:
    """(run time, wall, driving process's CPU) of the runs done `way`, s."""
    cpu, started = _cpu_s(), time.perf_counter()
    rows = WAYS[way](todo, workers)
    wall = time.perf_counter() - started
    return sum(r["wall_s"] for r in rows), wall, _cpu_s() - cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=30)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    todo = [Job("field", "wedge", 3, seed) for seed in range(args.runs)]
    cal = Calibration.measure()
    ways = list(WAYS)
    run_time: dict[str, list[float]] = {w: [] for w in ways}
    print(f"{'round':>5}  {'way':<22}{'run time':>10}{'wall':>9}{'driver CPU':>12}  load")
    for k in range(args.rounds):
        for way in ways if k % 2 == 0 else ways[::-1]:
            runs_s, wall_s, cpu_s = measure(way, todo, args.workers)
            run_time[way].append(runs_s)
            print(f"{k:>5}  {way:<22}{runs_s:>9.1f}s{wall_s:>8.1f}s{cpu_s:>11.2f}s  {load()}")
    pool = run_time["process pool"]
    for way in ways[:-1]:
        ratios = [a / b for a, b in zip(run_time[way], pool, strict=True)]
        shown = " ".join(f"{r:.3f}" for r in ratios)
        print(f"{way} / pool, run time: {shown}; median {statistics.median(ratios):.3f}")
    print(f"run time per run, pool (median): {statistics.median(pool) / args.runs:.2f} s, "
          f"{cal.cal(statistics.median(pool) / args.runs)}")  # fmt: skip
    Calibration.measure()


if __name__ == "__main__":
    main()
