"""Where a pose estimator's NEES goes out of its band: per robot of a run with the
estimator on, the error of its published pose against the run's truth along and across
its track and in heading, beside the standard deviations its covariance claimed, the
share of steps inside the 95 % band, and the NEES of the position (its 2 x 2 block of
the covariance) and of the heading alone.

    .venv/bin/python bench/bench_estimate_honesty.py RESULTS_FOLDER [RESULTS_FOLDER ...]

Reads each folder's `traces.npz` (a run with `[localisation] estimator = true` keeps the
estimates there); steps from `--from-s` on (the scenarios' settling time, 30 s).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from phalanx.analysis.estimation import NEES_BAND, nees, pose_errors
from phalanx.analysis.results import read_run_traces
from phalanx.core.runlog import FloatArray, RobotTrace

HEADER = (
    "| run | robot | rms error along / across (mm), heading (deg) | claimed sd x / y (mm), "
    "heading (deg), median | NEES in band | median NEES: whole / position / heading |\n"
    "|---|---|---|---|---|---|"
)


def _rms(values: FloatArray) -> float:
    return float(np.sqrt(np.nanmean(values * values)))


def row(run: str, robot_id: str, trace: RobotTrace, steps: FloatArray) -> str:
    """One robot's line of the table, over the steps `steps` selects."""
    _, heading_rad, errors = pose_errors(trace)
    cos, sin = np.cos(trace.theta_rad), np.sin(trace.theta_rad)
    along = errors[:, 0] * cos + errors[:, 1] * sin
    across = -errors[:, 0] * sin + errors[:, 1] * cos
    cov = trace.cov
    whole = nees(errors, cov)[steps]
    ex, ey, xx, xy, yy = errors[:, 0], errors[:, 1], cov[:, 0], cov[:, 1], cov[:, 3]
    position = ((yy * ex * ex - 2 * xy * ex * ey + xx * ey * ey) / (xx * yy - xy * xy))[steps]
    heading = (heading_rad**2 / cov[:, 5])[steps]
    finite = whole[np.isfinite(whole)]
    inside = float(np.mean((finite >= NEES_BAND[0]) & (finite <= NEES_BAND[1])))
    sd = np.sqrt(np.nanmedian(cov[steps][:, [0, 3, 5]], axis=0))
    return (
        f"| {run} | {robot_id} | {_rms(along[steps]) * 1e3:.2f} / "
        f"{_rms(across[steps]) * 1e3:.2f}, {np.degrees(_rms(heading_rad[steps])):.3f} | "
        f"{sd[0] * 1e3:.2f} / {sd[1] * 1e3:.2f}, {np.degrees(sd[2]):.3f} | "
        f"{inside * 100:.0f} % | {np.nanmedian(whole):.1f} / {np.nanmedian(position):.1f} / "
        f"{np.nanmedian(heading):.1f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="+", type=Path)
    parser.add_argument("--from-s", type=float, default=30.0)
    args = parser.parse_args()
    print(HEADER)
    for folder in args.folders:
        t_s, traces = read_run_traces(folder / "traces.npz")
        for robot_id, trace in traces.items():
            if np.isfinite(trace.cov).any():
                print(row(folder.name, robot_id, trace, t_s >= args.from_s))


if __name__ == "__main__":
    main()
