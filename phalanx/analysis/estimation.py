"""How well each robot knew where it was: its published pose (its estimate, with the pose
estimator on) against ground truth, and whether the covariance it published was honest.

Honesty is the normalised estimation error squared, NEES = e^T P^-1 e with e the pose
error (x, y, heading) and P the published covariance: for a consistent filter it follows
a chi-square law with 3 degrees of freedom, so about 95 % of steps fall inside the
two-sided 95 % band [0.216, 9.35] (`NEES_BAND`). Fewer inside from above means an
overconfident filter (it claims to know more than it does), from below a pessimistic one.
Measured from `initial_settle_s` (the start pose is given, not estimated).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from phalanx.core.runlog import RobotTrace, RunLog

FloatArray = npt.NDArray[np.float64]
# chi-square, 3 degrees of freedom: the 2.5 % and 97.5 % quantiles, and the 95 % one.
NEES_BAND = (0.2158, 9.3484)
NEES_UPPER_95 = 7.8147


def pose_errors(trace: RobotTrace) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per step: position error (m), heading error (rad, wrapped) and the error vector
    (n x 3) of the published pose against ground truth.
    """
    ex = trace.estimate[:, 0] - trace.x_m
    ey = trace.estimate[:, 1] - trace.y_m
    et = np.mod(trace.estimate[:, 2] - trace.theta_rad + math.pi, 2 * math.pi) - math.pi
    return np.hypot(ex, ey), et, np.column_stack([ex, ey, et])


def nees(errors: FloatArray, cov6: FloatArray) -> FloatArray:
    """e^T P^-1 e per step (NaN where no covariance was published or it is singular)."""
    xx, xy, xt, yy, yt, tt = (cov6[:, i] for i in range(6))
    p = np.stack(
        [np.stack([xx, xy, xt], -1), np.stack([xy, yy, yt], -1), np.stack([xt, yt, tt], -1)], -2
    )
    out = np.full(len(errors), np.nan)
    ok = np.all(np.isfinite(cov6), axis=1) & (np.abs(np.linalg.det(np.nan_to_num(p))) > 1e-300)
    if ok.any():
        solved = np.linalg.solve(p[ok], errors[ok][:, :, None])[:, :, 0]
        out[ok] = np.einsum("ij,ij->i", errors[ok], solved)
    return out


def robot_estimation(log: RunLog, robot_id: str) -> dict[str, Any]:
    """One robot's estimation errors and its filter's honesty."""
    trace = log.traces[robot_id]
    if trace.estimate.shape[0] != len(log.t_s):
        return {}
    settled = log.t_s >= log.scenario.initial_settle_s
    pos, head, vec = pose_errors(trace)
    value = nees(vec, trace.cov)[settled]
    finite = value[np.isfinite(value)]
    inside = (finite >= NEES_BAND[0]) & (finite <= NEES_BAND[1])
    return {
        "position_m": _stat(pos[settled]),
        "heading_deg": _stat(np.degrees(np.abs(head[settled]))),
        "final_position_m": _last(pos),
        "nees_steps": int(finite.size),
        "nees_mean": float(finite.mean()) if finite.size else math.nan,
        "nees_in_band": float(inside.mean()) if finite.size else math.nan,
        "nees_below_upper": float((finite <= NEES_UPPER_95).mean()) if finite.size else math.nan,
    }


def estimation_metrics(log: RunLog) -> dict[str, Any]:
    """Every robot's `robot_estimation`, and the share of all robots' steps in the band."""
    robots = {rid: robot_estimation(log, rid) for rid in log.traces}
    steps = sum(r.get("nees_steps", 0) for r in robots.values())
    inside = sum(
        r["nees_in_band"] * r["nees_steps"] for r in robots.values() if r.get("nees_steps")
    )
    return {"robots": robots, "nees_in_band": inside / steps if steps else math.nan}


def drift_cm_per_m(log: RunLog, robot_id: str) -> float:
    """The final position error of `robot_id`'s published pose per metre it drove (cm/m)."""
    trace = log.traces[robot_id]
    driven_m = float(np.sum(np.hypot(np.diff(trace.x_m), np.diff(trace.y_m))))
    pos, _, _ = pose_errors(trace)
    return 100.0 * _last(pos) / driven_m if driven_m > 0 else math.nan


def _last(values: FloatArray) -> float:
    """The last finite value (NaN: none; a robot publishes no pose for a tick it skips)."""
    finite = values[np.isfinite(values)]
    return float(finite[-1]) if finite.size else math.nan


def _stat(values: FloatArray) -> dict[str, float]:
    values = values[np.isfinite(values)]
    if values.size == 0:
        return {"max": math.nan, "mean": math.nan, "rms": math.nan}
    return {
        "max": float(values.max()),
        "mean": float(values.mean()),
        "rms": float(np.sqrt(np.mean(values**2))),
    }
