"""A run's results folder: `metrics.json`, the paper's figures as PNGs and the traces
they are drawn from (`traces.npz`), a Rerun `.rrd`.

`phalanx run` (in process) and `phalanx up` (one process per robot) both write it. A run
of processes is also marked whole or not (`mark_results`): `complete`, and the
`incomplete_reason` (a process died, the world did not run every tick); when the world
itself died, `metrics.json` holds that mark alone, beside what survived (the recording
parts, merged into `run.rrd`).
"""

from __future__ import annotations

import json
import math
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from phalanx.analysis.figures import write_figures
from phalanx.analysis.metrics import error_series, is_follower, run_metrics
from phalanx.core.limits import KinematicLimits
from phalanx.core.runlog import RunLog
from phalanx.core.scenarios import resolve_world


def _finite(value: Any) -> Any:
    """JSON has no NaN: empty statistics become null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


def write_metrics(metrics: dict[str, Any], path: Path) -> None:
    """Write metrics as JSON (NaN as null)."""
    path.write_text(json.dumps(_finite(metrics), indent=2) + "\n", encoding="utf-8")


def write_recording(log: RunLog, path: Path, *, recording_id: str | None = None) -> None:
    """Log the whole run to an `.rrd` file in columns (world, every robot, transitions)."""
    from phalanx.telemetry.sinks import TelemetrySink
    from phalanx.telemetry.stream import PAPER_ANGULAR_BOUND_PCT, PAPER_LINEAR_BOUND_PCT, Telemetry

    sink = TelemetrySink(kind="file", path=path)
    with Telemetry(recording_id=recording_id or str(uuid.uuid4()), sink=sink) as tel:
        world = resolve_world(log.scenario.world)  # a seeded field as its circles
        tel.log_world(
            circles=[(c.x_m, c.y_m, c.radius_m) for c in world.circles],
            polygons=[list(p.vertices_m) for p in world.polygons],
        )
        limits = KinematicLimits.from_params(log.robot, log.scenario.limits)
        tel.log_bounds(
            t_s=[float(log.t_s[0]), float(log.t_s[-1])],
            linear_pct=PAPER_LINEAR_BOUND_PCT,
            angular_pct=PAPER_ANGULAR_BOUND_PCT,
            v_max_mps=limits.v_max_mps,
            omega_max_radps=limits.omega_max_radps,
        )
        for rid, tr in log.traces.items():
            nan = np.full(len(log.t_s), np.nan)
            if not is_follower(log, rid):
                errors = (nan, nan, nan)
            else:
                s = error_series(log, rid)
                errors = (s.linear_pct, s.angular_pct, s.orientation_deg)
            tel.log_columns(
                rid,
                t_s=log.t_s,
                x_m=tr.x_m,
                y_m=tr.y_m,
                theta_rad=tr.theta_rad,
                cmd_v=tr.cmd_v_mps,
                cmd_omega=tr.cmd_omega_radps,
                meas_v=tr.v_mps,
                meas_omega=tr.omega_radps,
                linear_pct=errors[0],
                angular_pct=errors[1],
                orientation_deg=errors[2],
            )
            if tr.cov.shape[0] == len(log.t_s):
                tel.log_estimates(
                    rid,
                    t_s=log.t_s,
                    estimate=tr.estimate,
                    cov=tr.cov,
                    truth_xy=np.column_stack([tr.x_m, tr.y_m]),
                )
            for event in log.transitions[rid]:
                tel.log_transition(
                    rid,
                    t_s=event.t_s,
                    source=event.source,
                    target=event.target,
                    reason=event.reason,
                )
        tel.send_blueprint()


TRACE_FIELDS = ("x_m", "y_m", "theta_rad", "v_mps", "omega_radps", "cmd_v_mps", "cmd_omega_radps")


def write_traces(log: RunLog, path: Path) -> None:
    """Every robot's recorded motion, one row per control step, as a compressed numpy
    archive: `t_s`, then `<robot>/<field>` for each of TRACE_FIELDS (SI units) and
    `<robot>/state` (its behaviour state's name).
    """
    arrays: dict[str, Any] = {"t_s": log.t_s}
    for rid, trace in log.traces.items():
        for name in TRACE_FIELDS:
            arrays[f"{rid}/{name}"] = getattr(trace, name)
        arrays[f"{rid}/state"] = np.array(trace.states, dtype=np.str_)
    with path.open("wb") as out:
        np.savez_compressed(out, **arrays)


def read_traces(path: Path) -> dict[str, dict[str, Any]]:
    """A `traces.npz` back: robot -> field -> array, and "" -> {"t_s": times}."""
    with np.load(path, allow_pickle=False) as data:
        out: dict[str, dict[str, Any]] = {"": {"t_s": data["t_s"]}}
        for key in data.files:
            rid, _, name = key.rpartition("/")
            if rid:
                out.setdefault(rid, {})[name] = data[key]
    return out


def write_results(
    log: RunLog, folder: Path, *, recording: bool = True, figures: bool = True
) -> dict[str, Any]:
    """Write the results folder of `log` (without the PNG figures and the traces they
    are drawn from if not `figures`, and without the recording if not `recording`);
    returns the metrics.
    """
    folder.mkdir(parents=True, exist_ok=True)
    metrics = run_metrics(log)
    write_metrics(metrics, folder / "metrics.json")
    if figures:
        write_figures(log, folder)
        write_traces(log, folder / "traces.npz")
    if recording:
        write_recording(log, folder / "run.rrd")
    return metrics


def mark_results(folder: Path, *, problems: list[str]) -> dict[str, Any]:
    """Mark the results folder of a run of processes complete or not, with the reasons
    (`problems`: the supervisor's, and the world's own in `runtime`); returns the metrics.

    Writes `metrics.json` with the mark alone if the world wrote none (it died).
    """
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "metrics.json"
    try:
        metrics: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        metrics = {}
        problems = [*problems, "the world wrote no metrics (it died before the run's end)"]
    runtime = metrics.get("runtime")
    reasons = list(problems)
    if isinstance(runtime, dict) and runtime.get("incomplete_reason"):
        reasons.append(str(runtime["incomplete_reason"]))
    metrics["complete"] = not reasons
    metrics["incomplete_reason"] = "; ".join(reasons)
    write_metrics(metrics, path)
    return metrics
