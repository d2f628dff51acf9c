"""How a navigating group backs out where its way is blocked in the seeded fields: the
formation errors of its deadlock reverses, against the bounds the paper's reverses keep.

Runs `Job("field", shape, robots, seed)` as `phalanx sweep` does, for every seed of the
range, and prints each run that backed out at least once: its deadlock reverses, the
shape the group reversed in, and the worst follower's backward-phase errors as
`metrics.json` gives them (from 5 s after the leader turns back to the end of the
reverse; a reverse shorter than that is not measured), with the count of measured runs
inside `phalanx.analysis.metrics.CORE_BOUNDS` per formation. `--out FILE` also writes
every run's row as `phalanx sweep --out FILE` does, so that the same runs give the
sweep's table (`phalanx sweep` with the same options and `--out FILE` finds them done)
and pair with another sweep's (`phalanx sweep-compare`).

    .venv/bin/python bench/bench_field_reverses.py [--shape wedge collateral]
        [--robots 3 5] [--seeds 10 30] [--workers 2] [--set deadlock.pause_s=12]
        [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from phalanx.analysis.metrics import (
    CORE_BOUNDS,
    follower_metrics,
    leader_shape_keys,
    phase_masks,
)
from phalanx.analysis.sweep import Job, job_row, run_until_done
from phalanx.core.config_files import parse_assignment
from phalanx.core.errors import ConfigError
from phalanx.core.shapes import SCENARIO_SHAPE, ShapeBook, ShapeKey
from phalanx.runtime.batch import BatchRunner


@dataclass(frozen=True)
class Reversed:
    """One run's deadlock reverses and its worst follower's backward-phase errors."""

    job: Job
    reverses: int
    samples: int  # backward-phase steps measured (all followers)
    shapes: tuple[str, ...]  # the shapes the group reversed in, by name
    worst: dict[str, float]  # per error: the worst follower's maximum

    @property
    def within(self) -> bool:
        """Every error inside the bounds."""
        return all(self.worst[k] < bound for k, bound in CORE_BOUNDS.items())


def reverses_of(job: Job) -> tuple[Reversed, dict[str, Any]]:
    """Run `job`, measure its reverses, and give its sweep row."""
    started = time.perf_counter()
    log = run_until_done(BatchRunner(job.scenario()))
    row = job_row(job, log, time.perf_counter() - started)
    reverses = int(row["deadlock_reverses"])
    worst = dict.fromkeys(CORE_BOUNDS, 0.0)
    samples = 0
    for follower in log.traces:
        if follower == log.formation.root:
            continue
        backward = follower_metrics(log, follower)["backward"]
        samples += backward["samples"]
        if backward["samples"]:
            for key in CORE_BOUNDS:
                worst[key] = max(worst[key], backward[key]["max"])
    _, backing = phase_masks(log)
    keys = leader_shape_keys(log)
    column = ShapeBook(log.formation).distinct[-1]
    shapes = sorted({_shape_name(keys[k], column) for k in np.flatnonzero(backing).tolist()})
    return Reversed(job, reverses, samples, tuple(shapes), worst), row


def _shape_name(key: ShapeKey, column: int) -> str:
    """The shape the group was in (or sliding to), by name."""
    if key.target == SCENARIO_SHAPE:
        return "its shape" if key.settled else "sliding back into its shape"
    return "the column" if key.target == column else "a shrunk shape"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shape", nargs="+", default=["wedge", "collateral"])
    parser.add_argument("--robots", nargs="+", type=int, default=[3, 5])
    parser.add_argument("--seeds", nargs=2, type=int, default=[10, 30], metavar=("FIRST", "END"))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--set", nargs="*", default=[], metavar="PATH=VALUE")
    parser.add_argument("--out", type=Path, help="also write every run's sweep row here")
    args = parser.parse_args()
    try:
        overrides = tuple(parse_assignment(a) for a in args.set)
    except ConfigError as exc:
        raise SystemExit(str(exc)) from None
    jobs = [
        Job("field", shape, robots, seed, overrides=overrides)
        for shape in args.shape
        for robots in args.robots
        for seed in range(*args.seeds)
    ]
    with ProcessPoolExecutor(args.workers) as pool:
        done = list(pool.map(reverses_of, jobs))
    if args.out is not None:
        with args.out.open("a", encoding="utf-8") as out:
            out.writelines(json.dumps(row, allow_nan=True) + "\n" for _, row in done)
    runs = [r for r, _ in done if r.reverses]
    bounds = " / ".join(f"{v:g}" for v in CORE_BOUNDS.values())
    print("runs that backed out (worst follower's backward max: linear % / angular % / deg;")
    print(f"bounds {bounds}):")
    for r in runs:
        errors = " / ".join(f"{r.worst[k]:.2f}" for k in CORE_BOUNDS) if r.samples else "-"
        print(
            f"  {r.job.shape} of {r.job.robots}, seed {r.job.seed}: {r.reverses} reverse(s), "
            f"{r.samples} follower-steps measured, in {', '.join(r.shapes) or '-'}: {errors}"
        )
    for shape in args.shape:
        for robots in args.robots:
            mine = [r for r in runs if r.job.shape == shape and r.job.robots == robots]
            measured = [r for r in mine if r.samples]
            inside = sum(r.within for r in measured)
            print(
                f"{shape} of {robots}: {len(mine)} runs backed out, {len(measured)} measured,"
                f" {inside} inside the bounds"
            )


if __name__ == "__main__":
    main()
