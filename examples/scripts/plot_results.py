"""Plot a results folder: the robots' paths, and how far each follower keeps from the
robot it follows against the distance the scenario's slot asks for.

Reads `metrics.json` (who follows whom, the slot's distance `l_d_m`) and `traces.npz`
(every robot's pose and behaviour state at every control step) of a results folder, as
`phalanx run`, `phalanx up` and examples/scripts/run_scenario.py write them (`phalanx run`
writes traces.npz with its figures, so not with --no-figures), and saves one PNG. The
leader's deadlock reverses are shaded. Where the group folded into a column or shrank its
shape (RESHAPE), the distances follow that shape, not the scenario's.

Run:
    .venv/bin/python examples/scripts/plot_results.py results/api-deadlock \
        --out results/api-deadlock/separations.png
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from matplotlib.figure import Figure

from phalanx.analysis.results import read_traces

Traces = dict[str, dict[str, Any]]


def read(folder: Path) -> tuple[dict[str, Any], Traces]:
    """The metrics and the traces of a results folder."""
    metrics = json.loads((folder / "metrics.json").read_text(encoding="utf-8"))
    return metrics, read_traces(folder / "traces.npz")


def separation_m(traces: Traces, robot: str, other: str) -> npt.NDArray[np.float64]:
    """The distance between two robots at every step (m)."""
    a, b = traces[robot], traces[other]
    return np.asarray(np.hypot(a["x_m"] - b["x_m"], a["y_m"] - b["y_m"]), dtype=np.float64)


def reversing(traces: Traces, leader: str) -> npt.NDArray[np.bool_]:
    """The steps the leader spent backing the group out of a deadlock."""
    return np.asarray(traces[leader]["state"] == "DEADLOCK_REVERSE")


def plot(metrics: dict[str, Any], traces: Traces, out: Path) -> Path:
    """Draw the paths and the separations into `out` (PNG)."""
    t_s = traces[""]["t_s"]
    fig = Figure(figsize=(12, 4.5), layout="constrained")  # no pyplot: no display needed
    paths, gaps = fig.subplots(1, 2)
    for robot in sorted(r for r in traces if r):
        paths.plot(traces[robot]["x_m"], traces[robot]["y_m"], label=robot)
    paths.set(xlabel="x (m)", ylabel="y (m)", title="paths")
    paths.set_aspect("equal", adjustable="datalim")
    paths.legend()
    for robot, follower in metrics["followers"].items():
        line = gaps.plot(t_s, separation_m(traces, robot, follower["leader"]), label=robot)[0]
        gaps.axhline(follower["l_d_m"], color=line.get_color(), linestyle=":")
    leader = metrics["leader"]["id"]
    gaps.fill_between(
        t_s, 0, 1, where=reversing(traces, leader), transform=gaps.get_xaxis_transform(),
        color="0.85", label="deadlock reverse",
    )  # fmt: skip
    gaps.set(xlabel="t (s)", ylabel="distance to the robot followed (m)")
    gaps.set_title(f"{metrics['scenario']}: separations (dotted: the scenario's slots)")
    gaps.legend()
    fig.savefig(out, dpi=100)
    return out


def main(argv: list[str] | None = None) -> None:
    """Parse the command line, read the folder, plot."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, help="a results folder")
    parser.add_argument("--out", type=Path, help="the PNG (default: FOLDER/separations.png)")
    args = parser.parse_args(argv)
    metrics, traces = read(args.folder)
    out = plot(metrics, traces, args.out or args.folder / "separations.png")
    sys.stdout.write(f"wrote {out}\n")


if __name__ == "__main__":
    main()
