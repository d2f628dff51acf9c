"""`phalanx run` of a large fleet, phase by phase: what a user waits for.

The paper scenario's grid formation of N robots (`grid_scenario`), 20 s simulated,
taken through the same steps as `phalanx run` (`run_batch`'s `BatchRunner`, then
`write_results`'s parts): building the runner, stepping it, the metrics, the four PNG
figures and the Rerun recording, each timed on its own, with the machine's load beside
it and every time as a ratio to the calibration workload timed in the same run
(`bench/calibration.py`). `phalanx run --no-figures` skips the figures' step.

    .venv/bin/python bench/bench_run.py [--robots 100 1000] [--seconds 20]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from calibration import Calibration, load

from phalanx.analysis.figures import write_figures
from phalanx.analysis.metrics import run_metrics
from phalanx.analysis.results import write_metrics, write_recording
from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.core.scenarios import grid_scenario
from phalanx.runtime.batch import BatchRunner

T = TypeVar("T")


def timed(work: Callable[[], T]) -> tuple[T, float]:
    """`work()`'s result and its wall time (s)."""
    started = time.perf_counter()
    result = work()
    return result, time.perf_counter() - started


def phases(n: int, seconds: float, folder: Path) -> dict[str, float]:
    """Wall time (s) of each step of `phalanx run` for an `n`-robot grid."""
    base = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
    scenario = grid_scenario(base, n, duration_s=seconds)
    runner, build = timed(lambda: BatchRunner(scenario))
    log, run = timed(runner.run)
    metrics, measure = timed(lambda: run_metrics(log))
    _, write = timed(lambda: write_metrics(metrics, folder / "metrics.json"))
    _, figures = timed(lambda: write_figures(log, folder))
    _, recording = timed(lambda: write_recording(log, folder / "run.rrd"))
    return {
        "build": build,
        "run": run,
        "metrics": measure + write,
        "figures": figures,
        "recording": recording,
    }


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--robots", type=int, nargs="+", default=[100, 1000])
    parser.add_argument("--seconds", type=float, default=20.0)
    args = parser.parse_args()
    cal = Calibration.measure()
    names = ("build", "run", "metrics", "figures", "recording")
    print(f"phalanx run's steps, grid formations, {args.seconds:.0f} s simulated; s (cal)")
    print(f"robots  {'  '.join(f'{n:>14s}' for n in names)}  {'total':>14s}  load")
    for n in args.robots:
        with tempfile.TemporaryDirectory() as tmp:
            times = phases(n, args.seconds, Path(tmp))
        cells = [*(times[k] for k in names), sum(times.values())]
        print(
            f"{n:6d}  {'  '.join(f'{t:6.2f} ({cal.ratio(t):5.0f})' for t in cells)}  {load()}",
            flush=True,
        )
    Calibration.measure()


if __name__ == "__main__":
    main()
