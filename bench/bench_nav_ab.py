"""A navigating robot-step of this checkout against another's (a before and after).

Each scenario runs to its end in a fresh process for each checkout, stepped by
`BatchRunner` as `phalanx run` steps it; the checkouts alternate, their order reversed
every round, so a change in the machine's speed or load falls on both. Each process
times its runs in CPU time and the calibration workload (`bench/calibration.py`) as
every benchmark times it: the figure is the cost per robot-step and its ratio to it.
Printed per scenario: the median of each checkout, and this checkout's time over the
other's round by round, with their median. Both checkouts run with this interpreter and
its libraries (the other's phalanx comes first on `PYTHONPATH`), the compiled kernels
(`phalanx.core.compiled`) loaded before the runs are timed where the checkout has them;
`--pythonpath . --other-env PHALANX_KERNELS=numpy` sets numba's kernels against numpy's.

    .venv/bin/python bench/bench_nav_ab.py --pythonpath OTHER_CHECKOUT [--rounds 4]
        [--other-env NAME=VALUE ...]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from calibration import Calibration, load

REPO = Path(__file__).resolve().parents[1]
SCENARIOS = ("nav_field_wedge3", "nav_field_collateral5")


def child(scenarios: list[str]) -> None:
    """In a fresh process: CPU seconds per robot-step of each scenario, and the
    calibration's seconds, as one JSON line.
    """
    from phalanx.agents.perception import SonarGeometry
    from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
    from phalanx.runtime.batch import BatchRunner

    try:
        from phalanx.agents.navigation import warm_kernels
    except ImportError:  # (a checkout from before the compiled kernels)
        pass
    else:
        warm_kernels(SonarGeometry.from_params(load_robot("p3dx")))  # (loaded before timing)
    out: dict[str, float] = {}
    for name in scenarios:
        runner = BatchRunner(load_scenario(CONFIG_ROOT / "scenarios" / f"{name}.toml"))
        started = time.process_time()
        runner.run()
        out[name] = (time.process_time() - started) / (runner.done * len(runner.agents))
    out["cal"] = Calibration.measure(quiet=True).seconds
    print(json.dumps(out))


def measure(checkout: Path, scenarios: list[str], extra: dict[str, str]) -> dict[str, float]:
    """One fresh process of `checkout`'s phalanx running `scenarios`, with `extra` in its
    environment.
    """
    env = {**os.environ, "PYTHONPATH": str(checkout), **extra}
    done = subprocess.run(
        [sys.executable, __file__, "--child", *scenarios],
        cwd=checkout, env=env, capture_output=True, text=True, check=True, timeout=900,
    )  # fmt: skip
    result: dict[str, float] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pythonpath", type=Path, help="the other checkout (the 'before')")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--scenario", action="append", help="default: " + ", ".join(SCENARIOS))
    parser.add_argument(
        "--other-env", action="append", default=[], metavar="NAME=VALUE",
        help="set in the other's processes (e.g. PHALANX_KERNELS=numpy, with --pythonpath .)",
    )  # fmt: skip
    parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child)
        return
    if args.pythonpath is None:
        parser.error("--pythonpath OTHER_CHECKOUT is required")
    scenarios = args.scenario or list(SCENARIOS)
    trees = {"other": args.pythonpath.resolve(), "this": REPO}
    envs = {"other": dict(kv.split("=", 1) for kv in args.other_env), "this": {}}
    Calibration.measure()
    runs: dict[str, list[dict[str, float]]] = {name: [] for name in trees}
    for k in range(args.rounds):
        for name in list(trees) if k % 2 == 0 else list(reversed(trees)):
            runs[name].append(measure(trees[name], scenarios, envs[name]))
    for scenario in scenarios:
        line = [f"{scenario:24s}"]
        for name in trees:
            us = statistics.median(r[scenario] for r in runs[name]) * 1e6
            mcal = statistics.median(r[scenario] / r["cal"] for r in runs[name]) * 1e3
            line.append(f"{name} {us:6.1f} µs ({mcal:5.2f} mcal)")
        pairs = zip(runs["this"], runs["other"], strict=True)
        ratios = [this[scenario] / other[scenario] for this, other in pairs]
        line.append(f"this / other per round {[round(r, 3) for r in ratios]}")
        line.append(f"median {statistics.median(ratios):.3f}")
        print("  ".join(line))
    print(f"calibration: {load()}")


if __name__ == "__main__":
    main()
