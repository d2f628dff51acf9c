"""Run a scenario through phalanx's Python API and read its metrics.

Loads a scenario file, shortens it if asked (as `phalanx run --set duration_s=...` would),
runs every robot in this process, writes a results folder with `metrics.json` and
`traces.npz` (what examples/scripts/plot_results.py reads) and prints each follower's worst
formation errors, forwards and backwards, then the deadlock reverses and, for a navigating
leader, whether it reached its goal.

Run:
    .venv/bin/python examples/scripts/run_scenario.py examples/scenarios/deadlock_escape.toml \
        --out results/api-deadlock
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from phalanx.analysis.metrics import run_metrics
from phalanx.analysis.results import write_metrics, write_traces
from phalanx.core.config_files import apply_overrides, load_scenario
from phalanx.runtime.batch import run_batch


def run(scenario_path: Path, out: Path, *, duration_s: float | None = None) -> dict[str, Any]:
    """Run the scenario (cut to `duration_s` seconds if given), write `out`/metrics.json
    and `out`/traces.npz, and return the metrics.
    """
    scenario = load_scenario(scenario_path)
    if duration_s is not None:
        overrides = [f"duration_s={duration_s}"]
        scenario = apply_overrides(scenario, overrides, source=str(scenario_path))
    log = run_batch(scenario)
    metrics = run_metrics(log)
    out.mkdir(parents=True, exist_ok=True)
    write_metrics(metrics, out / "metrics.json")
    write_traces(log, out / "traces.npz")
    return metrics


def summary(metrics: dict[str, Any]) -> list[str]:
    """Lines to print: every follower's worst errors per phase, then the run's events."""
    lines = [f"{metrics['scenario']} ({metrics['controller']}), {metrics['duration_s']:g} s"]
    for robot, follower in metrics["followers"].items():
        for phase in ("forward", "backward"):
            errors = follower[phase]
            if errors["samples"] == 0:
                lines.append(f"  {robot} {phase:8}: not measured (the run had no {phase} phase)")
                continue
            lines.append(
                f"  {robot} {phase:8}: linear {errors['linear_pct']['max']:.3g} %, "
                f"angular {errors['angular_pct']['max']:.3g} %, "
                f"orientation {errors['orientation_deg']['max']:.3g} deg (max over "
                f"{errors['duration_s']:g} s, against {follower['leader']})"
            )
    lines.append(f"  deadlock reverses: {metrics['deadlock_reverses']}")
    lines.append(f"  collisions: {len(metrics['collisions'])}")
    navigation = metrics.get("navigation")
    if navigation is not None:
        reached = navigation["time_to_goal_s"]
        lines.append(f"  goal: reached at {reached:g} s" if reached else "  goal: not reached")
    return lines


def main(argv: list[str] | None = None) -> None:
    """Parse the command line, run, print the summary."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario", type=Path, help="a scenario file")
    parser.add_argument("--out", type=Path, default=Path("results/api-run"), help="results folder")
    parser.add_argument("--duration-s", type=float, help="run only this long (s)")
    args = parser.parse_args(argv)
    metrics = run(args.scenario, args.out, duration_s=args.duration_s)
    sys.stdout.write("\n".join([*summary(metrics), f"results: {args.out}"]) + "\n")


if __name__ == "__main__":
    main()
