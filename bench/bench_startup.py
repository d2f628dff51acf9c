"""How long the `phalanx` command takes to start: `phalanx --help`, and a one-second
`phalanx run` of the paper scenario without figures or recording, each a fresh process.

The time is measured from outside, as a user would: the wall time of the whole process.
Each command is run `--repeats` times, in rounds. Each round runs every command once,
together with a bare `python -c pass` as the yardstick: a figure is then given as a
ratio to Python's own start-up in the same rounds, which moves with the machine and its
load the way the command's start-up does. The calibration workload (`bench/calibration.py`)
is printed too. A second pass runs each command once under `python -X importtime`. It
lists the heavy libraries the command imports, and how long importing them took.

    .venv/bin/python bench/bench_startup.py [--repeats 10] [--pythonpath OTHER_CHECKOUT ...]

`--pythonpath` also times the phalanx of another checkout (for a before and after). It
uses the same interpreter and libraries, and runs in the same rounds.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "lab"))

from calibration import Calibration, load
from heavy_imports import HEAVY

REPO = Path(__file__).resolve().parents[1]
SCENARIO = REPO / "configs" / "scenarios" / "paper_wedge.toml"


def commands(out: Path) -> dict[str, list[str]]:
    """The arguments of each command timed (after `phalanx`)."""
    return {
        "phalanx --help": ["--help"],
        "phalanx run (1 s, no figures, no recording)": [
            "run", str(SCENARIO), "--set", "duration_s=1", "--no-figures", "--no-recording",
            "--out", str(out), "--force",
        ],
    }  # fmt: skip


def _launcher(args: list[str]) -> list[str]:
    """`phalanx ARGS`: the console script installed beside this interpreter."""
    return [sys.executable, str(Path(sys.executable).parent / "phalanx"), *args]


def wall_s(argv: list[str], env: dict[str, str]) -> float:
    """The wall time of one process (s); it must succeed."""
    started = time.perf_counter()
    subprocess.run(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
    return time.perf_counter() - started


def imported(args: list[str], env: dict[str, str]) -> dict[str, float]:
    """The heavy libraries `phalanx ARGS` imports, each with its cumulative import time (s)."""
    argv = [sys.executable, "-X", "importtime", *_launcher(args)[1:]]
    done = subprocess.run(argv, env=env, capture_output=True, text=True, check=True)
    found: dict[str, float] = {}
    for line in done.stderr.splitlines():
        parts = line.split("|")
        if len(parts) == 3 and parts[2].strip() in HEAVY:
            found[parts[2].strip()] = int(parts[1]) / 1e6
    return found


def _env(tree: Path | None) -> dict[str, str]:
    """The environment that runs the phalanx of `tree` (None: the installed one)."""
    env = dict(os.environ)
    if tree is not None:
        env["PYTHONPATH"] = str(tree.resolve())
    return env


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument(
        "--pythonpath", type=Path, nargs="*", default=[], help="other checkouts, timed alongside"
    )
    args = parser.parse_args()
    trees: dict[str, Path | None] = {"": None} | {f" [{p}]": p for p in args.pythonpath}
    cal = Calibration.measure()
    with tempfile.TemporaryDirectory() as folder:
        timed = {name: _launcher(a) for name, a in commands(Path(folder) / "run").items()}
        bare = [sys.executable, "-c", "pass"]
        times: dict[str, list[float]] = {"python -c pass": []}
        for _ in range(args.repeats):
            times["python -c pass"].append(wall_s(bare, _env(None)))
            for label, tree in trees.items():
                for name, argv in timed.items():
                    times.setdefault(name + label, []).append(wall_s(argv, _env(tree)))
        heavy = {
            name + label: imported(a, _env(tree))
            for label, tree in trees.items()
            for name, a in commands(Path(folder) / "run").items()
        }
    base = statistics.median(times["python -c pass"])
    print(f"median of {args.repeats} rounds; load {load()}")
    width = max(len(name) for name in times)
    print(f"{'command':{width}s} {'median':>8s} {'min':>8s} {'x python -c pass':>17s} {'cal':>6s}")
    for name, seconds in times.items():
        median = statistics.median(seconds)
        print(
            f"{name:{width}s} {median:7.3f}s {min(seconds):7.3f}s {median / base:16.1f}x "
            f"{cal.ratio(median):6.1f}"
        )
    for name, found in heavy.items():
        listed = ", ".join(f"{lib} {1e3 * s:.0f} ms" for lib, s in found.items()) or "none"
        print(f"{name}: imports {listed}")
    Calibration.measure()


if __name__ == "__main__":
    main()
