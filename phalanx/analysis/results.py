"""A run's results folder: `metrics.json`, the paper's figures (PNG, PDF or SVG; the four
also as one PDF, `paper.pdf`; and the estimation figure of a run with the pose estimator
on) and the traces they are drawn from (`traces.npz`), a Rerun `.rrd`.

`phalanx run` (in process) and `phalanx up` (one process per robot) both write it. A run
of processes is also marked whole or not (`mark_results`): `complete`, and the
`incomplete_reason` (a process died, the world did not run every tick); when the world
itself died, `metrics.json` holds what its last checkpoint computed (`write_checkpoint`:
the errors up to then) or, with none, that mark alone, beside what survived (the recording
parts, merged into `run.rrd`).

Every file is written whole or not at all: into a temporary file in the same folder,
then renamed over the old one (`atomic_write`). A write that fails (a full disk, a folder
that cannot be written) raises `ResultsNotWritten`, naming the folder and the files kept;
a `metrics.json` already there stays as it was.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
import uuid
import zipfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

# The figures' names only: the drawing (matplotlib) is imported when figures are drawn.
from phalanx.analysis.figure_files import (
    DEFAULT_DPI,
    ESTIMATION_FIGURE,
    FIGURE_FILES,
    FORMATS,
    PAPER_FIGURE,
    FigureFormat,
    figure_name,
)
from phalanx.analysis.metrics import error_series, is_follower, run_metrics
from phalanx.core.config import MAX_ROBOT_STEPS
from phalanx.core.errors import PhalanxError
from phalanx.core.files import atomic_write
from phalanx.core.limits import KinematicLimits
from phalanx.core.quantities import (
    MAX_DURATION_S,
    MAX_EXTENT_M,
    MAX_SPEED_MPS,
    MAX_YAW_RATE_RADPS,
)
from phalanx.core.runlog import FloatArray, RobotTrace, RunLog
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


RESULT_FILES = (
    "metrics.json",
    "traces.npz",
    "run.rrd",
    *(figure_name(name, fmt) for fmt in FORMATS for name in (*FIGURE_FILES, ESTIMATION_FIGURE)),
    PAPER_FIGURE,
)


class ResultsNotWritten(PhalanxError, OSError):
    """A results file could not be written (a full disk, a folder that cannot be written):
    the message names the folder, what failed and the files the folder keeps.
    """

    def __init__(self, folder: Path, what: str, cause: OSError) -> None:
        self.folder, self.what, self.cause = folder, what, cause
        self.kept = kept_files(folder)
        kept = ", ".join(self.kept) if self.kept else "nothing"
        why = cause.strerror or str(cause)
        super().__init__(f"could not write {what} to {folder}: {why} (kept there: {kept})")


def kept_files(folder: Path) -> list[str]:
    """What `folder` holds of a run's results: each results file that holds something
    (`metrics.json (2.1 KiB)`), and the recording parts in its sub-folders (`telemetry/
    (4 parts, 290.3 KiB)`: the processes' own, which `phalanx up` merges).
    """
    out = []
    for name in RESULT_FILES:
        with contextlib.suppress(OSError):
            size = (folder / name).stat().st_size
            if size > 0:
                out.append(f"{name} ({size / 1024:.1f} KiB)")
    with contextlib.suppress(OSError):
        for sub in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
            sizes = [part.stat().st_size for part in sub.glob("*.rrd")]
            if sizes:
                out.append(f"{sub.name}/ ({len(sizes)} parts, {sum(sizes) / 1024:.1f} KiB)")
    return out


def _guarded(folder: Path, what: str, write: Callable[[], object]) -> None:
    """Run `write`; an OSError becomes ResultsNotWritten for `what` in `folder`."""
    try:
        write()
    except ResultsNotWritten:
        raise
    except OSError as exc:
        raise ResultsNotWritten(folder, what, exc) from exc


def write_metrics(metrics: dict[str, Any], path: Path) -> None:
    """Write metrics as JSON (NaN as null), atomically."""
    text = json.dumps(_finite(metrics), indent=2) + "\n"
    atomic_write(path, lambda out: out.write(text.encode("utf-8")))


def write_recording(log: RunLog, path: Path, *, recording_id: str | None = None) -> None:
    """Log the whole run to an `.rrd` file in columns (world, every robot, transitions);
    written under a temporary name and renamed once the recording is closed.
    """
    partial = path.with_name(f".{path.name}.tmp")
    try:
        _record(log, partial, recording_id=recording_id)
        if partial.stat().st_size == 0:  # (the SDK logs a failed write; it does not raise)
            raise OSError(28, "the recording came out empty", str(path))
        os.replace(partial, path)
    finally:
        with contextlib.suppress(OSError):
            partial.unlink()


def _record(log: RunLog, path: Path, *, recording_id: str | None) -> None:
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
# What a trace read back may hold, field by field (NaN: a step a robot was not there):
# a file from elsewhere is held to what a run writes.
_TRACE_BOUNDS = {
    "x_m": MAX_EXTENT_M,
    "y_m": MAX_EXTENT_M,
    "theta_rad": 2 * math.pi,
    "v_mps": MAX_SPEED_MPS,
    "omega_radps": MAX_YAW_RATE_RADPS,
    "cmd_v_mps": MAX_SPEED_MPS,
    "cmd_omega_radps": MAX_YAW_RATE_RADPS,
}
# What a robot that estimates its pose published with it, per step: the estimate (x, y,
# theta) and its covariance's upper triangle (xx, xy, xt, yy, yt, tt), NaN where it
# published none (`RobotTrace.estimate`, `RobotTrace.cov`); columns and bounds.
ESTIMATE_FIELDS = {"estimate": 3, "cov": 6}
_TURN = 2 * math.pi
_AREA, _ARM = MAX_EXTENT_M**2, MAX_EXTENT_M * _TURN  # (m^2; m rad)
_ESTIMATE_BOUNDS = {
    "estimate": np.array([MAX_EXTENT_M, MAX_EXTENT_M, _TURN]),
    "cov": np.array([_AREA, _AREA, _ARM, _AREA, _ARM, _TURN**2]),  # xx, xy, xt, yy, yt, tt
}
# The most a `traces.npz` unpacks to: the largest run's (`MAX_ROBOT_STEPS`, each step its
# fields, its estimate and covariance and a state's name of up to 32 characters, and the
# step times), so that a small archive that unpacks to more is refused before it is read.
MAX_TRACES_BYTES = MAX_ROBOT_STEPS * (
    8 * (len(TRACE_FIELDS) + sum(ESTIMATE_FIELDS.values())) + 4 * 32 + 8
)


def write_traces(log: RunLog, path: Path) -> None:
    """Every robot's recorded motion, one row per control step, as a compressed numpy
    archive: `t_s`, then `<robot>/<field>` for each of TRACE_FIELDS (SI units) and
    `<robot>/state` (its behaviour state's name); of a robot that published an estimate
    of its pose, also `<robot>/estimate` and `<robot>/cov` (ESTIMATE_FIELDS).
    """
    arrays: dict[str, Any] = {"t_s": log.t_s}
    for rid, trace in log.traces.items():
        for name in TRACE_FIELDS:
            arrays[f"{rid}/{name}"] = getattr(trace, name)
        arrays[f"{rid}/state"] = np.array(trace.states, dtype=np.str_)
        if trace.cov.shape[0] == log.t_s.size and np.isfinite(trace.cov).any():
            arrays[f"{rid}/estimate"], arrays[f"{rid}/cov"] = trace.estimate, trace.cov
    atomic_write(path, lambda out: np.savez_compressed(out, **arrays))


def read_run_traces(path: Path) -> tuple[FloatArray, dict[str, RobotTrace]]:
    """A `traces.npz` back as the run's step times (s) and every robot's trace (the
    fields `write_traces` keeps; the rest empty, the estimates NaN where it kept none).
    KeyError or ValueError if it is not a run's, or holds a value no run writes (a step
    time not from 0 to a day, a value past its field's bound).
    """
    fields = read_traces(path)
    t_s = np.asarray(fields.pop("")["t_s"], dtype=float)
    if t_s.ndim != 1 or not np.all((t_s >= 0.0) & (t_s <= MAX_DURATION_S)):
        raise ValueError(f"t_s: step times must lie from 0 to {MAX_DURATION_S:g} s")
    traces = {}
    for rid, arrays in fields.items():
        trace = RobotTrace.empty(t_s.size)
        for name in TRACE_FIELDS:
            column = np.asarray(arrays[name], dtype=float)
            if column.shape != t_s.shape:
                raise ValueError(f"{rid}/{name}: {column.size} rows for {t_s.size} steps")
            bound = _TRACE_BOUNDS[name]
            if not np.all(np.isnan(column) | (np.abs(column) <= bound)):
                raise ValueError(f"{rid}/{name}: values beyond +-{bound:g}")
            setattr(trace, name, column)
        for name in ESTIMATE_FIELDS:
            if name in arrays:
                setattr(trace, name, _estimate_rows(arrays[name], rid, name, t_s.size))
        trace.states = [str(s) for s in arrays["state"]]
        traces[rid] = trace
    return t_s, traces


def _estimate_rows(array: Any, rid: str, name: str, steps: int) -> FloatArray:
    """Robot `rid`'s `name` (of ESTIMATE_FIELDS) read back, held to its shape and bounds."""
    rows = np.asarray(array, dtype=float)
    if rows.shape != (steps, ESTIMATE_FIELDS[name]):
        raise ValueError(
            f"{rid}/{name}: {rows.shape}, expected {steps} rows of {ESTIMATE_FIELDS[name]}"
        )
    if not np.all(np.isnan(rows) | (np.abs(rows) <= _ESTIMATE_BOUNDS[name])):
        raise ValueError(f"{rid}/{name}: values beyond what a pose or its covariance can be")
    return rows


def read_traces(path: Path) -> dict[str, dict[str, Any]]:
    """A `traces.npz` back: robot -> field -> array, and "" -> {"t_s": times}.
    ValueError if it is no numpy archive (empty, cut short, another kind of file) or
    unpacks to more than `MAX_TRACES_BYTES`.
    """
    try:
        with zipfile.ZipFile(path) as archive:
            unpacked = sum(member.file_size for member in archive.infolist())
        if unpacked > MAX_TRACES_BYTES:
            raise ValueError(f"unpacks to {unpacked} bytes, more than any run writes")
        with np.load(path, allow_pickle=False) as data:
            out: dict[str, dict[str, Any]] = {"": {"t_s": data["t_s"]}}
            for key in data.files:
                rid, _, name = key.rpartition("/")
                if rid:
                    out.setdefault(rid, {})[name] = data[key]
    except (zipfile.BadZipFile, EOFError) as exc:
        raise ValueError(f"not a numpy archive ({exc or 'empty'})") from exc
    return out


def write_figures_atomically(
    log: RunLog,
    folder: Path,
    *,
    fmt: FigureFormat = "png",
    dpi: int = DEFAULT_DPI,
    paper: bool = True,
) -> None:
    """The paper's figures as `fmt` files (`dpi`: a PNG's pixels per inch; with `paper`,
    also as one PDF), drawn into a temporary folder beside `folder`'s and moved in one by
    one: a figure is there whole or not at all.
    """
    from phalanx.analysis.figures import write_figures

    drafts = Path(tempfile.mkdtemp(dir=folder, prefix=".figures."))
    try:
        for path in write_figures(log, drafts, fmt=fmt, dpi=dpi, paper=paper):
            os.replace(path, folder / path.name)
    finally:
        shutil.rmtree(drafts, ignore_errors=True)


def write_results(
    log: RunLog,
    folder: Path,
    *,
    recording: bool = True,
    figures: bool = True,
    figure_format: FigureFormat = "png",
    dpi: int = DEFAULT_DPI,
    paper: bool = True,
) -> dict[str, Any]:
    """Write the results folder of `log` (without the figures and the traces they are
    drawn from if not `figures`, and without the recording if not `recording`; the
    figures as `figure_format` files, a PNG at `dpi`, and with `paper` the four as one
    PDF too); returns the metrics. The metrics first (the smallest and the most wanted),
    each file atomically; a write that fails raises ResultsNotWritten.
    """
    _guarded(folder, "the results folder", lambda: folder.mkdir(parents=True, exist_ok=True))
    metrics = run_metrics(log)
    _guarded(folder, "metrics.json", lambda: write_metrics(metrics, folder / "metrics.json"))
    if figures:
        _guarded(folder, "traces.npz", lambda: write_traces(log, folder / "traces.npz"))
        _guarded(
            folder,
            "the figures",
            lambda: write_figures_atomically(log, folder, fmt=figure_format, dpi=dpi, paper=paper),
        )
    if recording:
        _guarded(folder, "run.rrd", lambda: write_recording(log, folder / "run.rrd"))
    return metrics


def write_checkpoint(log: RunLog, folder: Path) -> None:
    """What a run still going has produced so far (`log`: its first ticks): `traces.npz`
    and then `metrics.json` marked incomplete, each atomically, so that a world that dies
    leaves the errors up to its last checkpoint. The metrics last: a world killed
    between the two leaves metrics that the traces beside them hold all of (never
    metrics of ticks the traces lack). Raises ResultsNotWritten.
    """
    _guarded(folder, "the results folder", lambda: folder.mkdir(parents=True, exist_ok=True))
    metrics = run_metrics(log)
    metrics["complete"] = False
    so_far = log.runtime.get("incomplete_reason") or f"{len(log.t_s)} ticks run"
    metrics["incomplete_reason"] = f"a checkpoint of a run still going: {so_far}"
    _guarded(folder, "traces.npz", lambda: write_traces(log, folder / "traces.npz"))
    _guarded(folder, "metrics.json", lambda: write_metrics(metrics, folder / "metrics.json"))


def mark_results(
    folder: Path, *, problems: Iterable[str], since_unix: float | None = None
) -> dict[str, Any]:
    """Mark the results folder of a run of processes complete or not, with the reasons
    (`problems`: the supervisor's, and the world's own in `runtime`); returns the metrics.

    Writes `metrics.json` with the mark alone if the world wrote none (it died before
    its first checkpoint), or only one older than `since_unix` (an earlier run's).
    Raises ResultsNotWritten if the mark cannot be written.
    """
    reasons = list(problems)
    _guarded(folder, "the results folder", lambda: folder.mkdir(parents=True, exist_ok=True))
    path = folder / "metrics.json"
    metrics = _read_metrics(path, since_unix)
    if metrics is None:
        metrics = {}
        reasons.append("the world wrote no metrics (it died before the run's end)")
    runtime = metrics.get("runtime")
    if isinstance(runtime, dict) and runtime.get("incomplete_reason"):
        reasons.append(str(runtime["incomplete_reason"]))
    metrics["complete"] = not reasons
    metrics["incomplete_reason"] = "; ".join(reasons)
    _guarded(folder, "metrics.json", lambda: write_metrics(metrics, path))
    return metrics


def _read_metrics(path: Path, since_unix: float | None) -> dict[str, Any] | None:
    """`metrics.json` as a dict (None: absent, unreadable, not an object, or older than
    `since_unix`).
    """
    try:
        if since_unix is not None and path.stat().st_mtime < since_unix:
            return None
        metrics = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return metrics if isinstance(metrics, dict) else None
