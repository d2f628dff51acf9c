"""What phalanx logs to Rerun: per-step rows turned into columns (one `send_columns` per
entity for a batch of steps costs a fraction of one `log` per entity per step; see
docs/PERFORMANCE.md). How it is laid out in the viewer is `phalanx.telemetry.blueprint`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.rigid_body import LiveErrors
from phalanx.core.robot_params import SonarParams
from phalanx.telemetry.blueprint import TRUTH_COLOUR
from phalanx.telemetry.uncertainty import ellipse, position_std_m, send_ellipses

FloatArray = npt.NDArray[np.float64]
Point = tuple[float, float]
POSE_RADIUS_M = 0.25
HEADING_LENGTH_M = 0.4
SONAR_RAY_RADIUS_M = 0.005
ERROR_NAMES = ("linear_pct", "angular_pct", "orientation_deg")
log = logging.getLogger("phalanx.telemetry")


# The slot target and the errors of a step that tracks a leader, or what computes them
# when the batch goes out (on the telemetry thread, off the control step).
Tracking = LiveErrors | Callable[[], LiveErrors]


@dataclass(frozen=True, slots=True)
class StepRow:
    """One robot's control step as logged: where it is, what it does, how it does.

    Only what the step has at hand is kept: labels and sonar rays are made for a whole
    batch of rows when it goes out (`send_step_rows`), off the control step.
    """

    t_s: float
    step: int
    pose: Pose2D
    cmd: Twist2D
    measured: Twist2D
    fsm_state: str = ""
    leader_id: str = ""
    tracking: Tracking | None = None
    sonar_ranges_m: Sequence[float] = ()
    trail: tuple[Point, ...] | None = None  # the trail to redraw at this step, if any
    cov: tuple[float, ...] = ()  # the pose's covariance, when the robot estimates it

    def label(self, robot_id: str) -> str:
        """The text beside the robot on the map: its id, state and leader."""
        leader = f" -> {self.leader_id}" if self.leader_id else ""
        return f"{robot_id} {self.fsm_state}{leader}"


@dataclass(frozen=True, slots=True)
class TruthRow:
    """A robot's ground-truth position at one step (the world process)."""

    t_s: float
    x_m: float
    y_m: float


def _rr() -> Any:
    import rerun  # heavy: imported only when telemetry is on

    return rerun


def _indexes(t_s: Sequence[float], steps: Sequence[int] | None = None) -> list[Any]:
    rr = _rr()
    times = [rr.TimeColumn("sim_time", duration=np.asarray(t_s, dtype=np.float64))]
    if steps is not None:
        times.append(rr.TimeColumn("step", sequence=np.asarray(steps, dtype=np.int64)))
    return times


def send_step_rows(
    rec: Any, robot_id: str, rows: Sequence[StepRow], sonar: SonarParams | None = None
) -> None:
    """Every entity of `robots/<id>/` for a batch of steps, one column send per entity
    (the sonar rays from `sonar`'s geometry and each row's ranges; none without it).
    """
    rr, base = _rr(), f"robots/{robot_id}"
    index = _indexes([r.t_s for r in rows], [r.step for r in rows])
    poses = np.array([(r.pose.x_m, r.pose.y_m, r.pose.theta_rad) for r in rows], np.float64)
    xy, theta = poses[:, :2], poses[:, 2]
    heading = HEADING_LENGTH_M * np.column_stack([np.cos(theta), np.sin(theta)])
    pose = rr.Points2D.columns(
        positions=xy,
        radii=np.full(len(rows), POSE_RADIUS_M),
        labels=[r.label(robot_id) for r in rows],
    )
    rec.send_columns(f"{base}/pose", indexes=index, columns=pose)
    arrows = rr.Arrows2D.columns(vectors=heading, origins=xy)
    rec.send_columns(f"{base}/heading", indexes=index, columns=arrows)
    twists = {
        "cmd/v_mps": [r.cmd.v_mps for r in rows],
        "cmd/omega_degps": [math.degrees(r.cmd.omega_radps) for r in rows],
        "measured/v_mps": [r.measured.v_mps for r in rows],
        "measured/omega_degps": [math.degrees(r.measured.omega_radps) for r in rows],
    }
    for name, values in twists.items():
        rec.send_columns(
            f"{base}/{name}", indexes=index, columns=rr.Scalars.columns(scalars=values)
        )
    if sonar is not None:
        _send_rays(rec, base, sonar_segments(sonar, poses, [r.sonar_ranges_m for r in rows]), index)
    _send_tracking(rec, base, rows)
    if any(r.cov for r in rows):
        strips = [ellipse(r.pose.x_m, r.pose.y_m, r.cov) for r in rows]
        send_ellipses(rec, rr, f"{base}/covariance", index, strips)
        stds = [position_std_m(r.cov) for r in rows]
        rec.send_columns(
            f"{base}/estimate/std_m", indexes=index, columns=rr.Scalars.columns(scalars=stds)
        )
    for row in rows:
        if row.trail is not None:
            rec.set_time("sim_time", duration=row.t_s)
            rec.set_time("step", sequence=row.step)
            rec.log(f"{base}/trail", rr.LineStrips2D([list(row.trail)]))


def sonar_segments(
    sonar: SonarParams, poses: FloatArray, ranges_m: Sequence[Sequence[float]]
) -> tuple[FloatArray, list[int]]:
    """World-frame segments (m x 2 x 2: start, end) of the sonars that see something
    (range below the maximum) at each of the n poses (n x 3: x, y, theta), and how many
    each pose has. A row of ranges shorter than the ring leaves its last sonars unseen.
    """
    units = np.array([(u.x_m, u.y_m, math.radians(u.heading_deg)) for u in sonar.units])
    units = units.reshape(-1, 3)
    ranges = np.full((len(poses), len(units)), np.inf)
    for k, row in enumerate(ranges_m):
        count = min(len(row), len(units))
        ranges[k, :count] = row[:count]
    x, y, theta = (poses[:, i : i + 1] for i in range(3))
    cos, sin = np.cos(theta), np.sin(theta)
    start_x = x + cos * units[:, 0] - sin * units[:, 1]
    start_y = y + sin * units[:, 0] + cos * units[:, 1]
    heading = theta + units[:, 2]
    seen = ranges < sonar.max_range_m
    reach = np.where(seen, ranges, 0.0)
    end_x, end_y = start_x + reach * np.cos(heading), start_y + reach * np.sin(heading)
    segments = np.stack([start_x, start_y, end_x, end_y], axis=-1)[seen].reshape(-1, 2, 2)
    return segments, [int(n) for n in seen.sum(axis=1)]


def _send_rays(rec: Any, base: str, rays: tuple[FloatArray, list[int]], index: list[Any]) -> None:
    """Sonar rays; a step that sees nothing clears the previous step's rays."""
    segments, per_row = rays
    columns = _rr().LineStrips2D.columns(
        strips=segments, radii=np.full(len(segments), SONAR_RAY_RADIUS_M)
    )
    rec.send_columns(f"{base}/sonar", indexes=index, columns=columns.partition(per_row))


def _send_tracking(rec: Any, base: str, rows: Sequence[StepRow]) -> None:
    """The slot target and the errors, at the steps that have a leader to track."""
    rr = _rr()
    tracked = _resolved(rows)
    if not tracked:
        return
    index = _indexes([r.t_s for r, _ in tracked], [r.step for r, _ in tracked])
    targets = np.array([(e.slot_target.x_m, e.slot_target.y_m) for _, e in tracked])
    slot = rr.Points2D.columns(positions=targets, radii=np.full(len(tracked), 0.05))
    rec.send_columns(f"{base}/slot_target", indexes=index, columns=slot)
    for name in ERROR_NAMES:
        values = [getattr(e, name) for _, e in tracked]
        rec.send_columns(
            f"{base}/errors/{name}", indexes=index, columns=rr.Scalars.columns(scalars=values)
        )


def _resolved(rows: Sequence[StepRow]) -> list[tuple[StepRow, LiveErrors]]:
    """The rows that track a leader, with their slot target and errors. A row whose
    errors cannot be computed is left out: that costs the recording its point, not the
    batch, and the log one line a batch (with the first failure), not one a step.
    """
    tracked, failed, first = [], 0, None
    for row in rows:
        tracking = row.tracking
        if tracking is None:
            continue
        try:
            tracked.append((row, tracking if isinstance(tracking, LiveErrors) else tracking()))
        except Exception as exc:
            failed, first = failed + 1, first or exc
    if first is not None:
        log.error(
            "telemetry: the errors of %d of %d steps could not be computed", failed, len(rows),
            exc_info=first,
        )  # fmt: skip
    return tracked


def send_truth_rows(rec: Any, robot_id: str, rows: Sequence[TruthRow]) -> None:
    """Ground-truth positions of one robot for a batch of steps."""
    xy = np.array([(r.x_m, r.y_m) for r in rows], dtype=np.float64)
    colours = np.tile(np.array(TRUTH_COLOUR, np.uint8), (len(rows), 1))
    points = _rr().Points2D.columns(positions=xy, radii=np.full(len(rows), 0.05), colors=colours)
    rec.send_columns(
        f"world/truth/{robot_id}", indexes=_indexes([r.t_s for r in rows]), columns=points
    )
