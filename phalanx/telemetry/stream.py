"""Rerun telemetry: one recording per fleet run, shared by every process by its id.

Entity layout (units and frames in the names):
    world/obstacles                      static outlines
    world/truth/<id>                     ground-truth position (the world process)
    robots/<id>/pose, /heading, /trail   where the robot believes it is (its estimate)
    robots/<id>/covariance               its estimate's 2-sigma ellipse (pose estimator on)
    robots/<id>/estimate/{std_m,error_m} its sigma, and (batch runs) its error on the truth
    robots/<id>/slot_target              the rigid-body target it tracks
    robots/<id>/sonar                    sonar rays in the world frame
    robots/<id>/cmd/{v_mps,omega_degps}  commanded twist
    robots/<id>/measured/{v_mps,omega_degps}
    robots/<id>/errors/{linear_pct,angular_pct,orientation_deg}
    robots/<id>/fsm                      state transitions (text log)
    robots/<id>/state                    behaviour state over time (the paper's figure 4b)
    bounds/...                           the paper's error bounds and the velocity limits
    frames/map_y_up                      the map view's frame: the world mirrored in y
Timelines: `sim_time` (s) and `step`.

Entries reach the sinks through the bounded outbox of `phalanx.telemetry.sinks`, so
logging never blocks a control step. The layout (`phalanx.telemetry.blueprint`) draws the
map y up and each robot in one colour across every view.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.lifecycle import Closing
from phalanx.core.robot_params import SonarParams
from phalanx.telemetry.blueprint import MAP_FRAME_ENTITY, make_blueprint, map_frame_transform
from phalanx.telemetry.layout import (
    POSE_RADIUS_M,
    StepRow,
    Tracking,
    TruthRow,
    send_step_rows,
    send_truth_rows,
)
from phalanx.telemetry.sinks import Outbox, TelemetrySink, rerun_sdk
from phalanx.telemetry.uncertainty import ellipse, position_std_m, send_ellipses

FloatArray = npt.NDArray[np.float64]
TRAIL_POINTS = 600
TRAIL_EVERY_STEPS = 10
BOUND_SAMPLES = 121  # the bounds are drawn as dots: this many over the run
# Section 5 of the paper: backward-motion errors below 2 % linear and 0.8 % angular.
PAPER_LINEAR_BOUND_PCT = 2.0
PAPER_ANGULAR_BOUND_PCT = 0.8


class _Extent:
    """The bounding box of every position logged, to frame the map at the end of a run."""

    def __init__(self) -> None:
        self.box: list[float] | None = None  # x_min, x_max, y_min, y_max

    def add(self, x_m: FloatArray, y_m: FloatArray) -> None:
        """Grow the box to include the given positions."""
        if x_m.size == 0:
            return
        self._grow(float(x_m.min()), float(x_m.max()), float(y_m.min()), float(y_m.max()))

    def add_point(self, x_m: float, y_m: float) -> None:
        """Grow the box to include one position (a control step's: no array made)."""
        b = self.box
        if b is None or not (b[0] <= x_m <= b[1] and b[2] <= y_m <= b[3]):
            self._grow(x_m, x_m, y_m, y_m)

    def _grow(self, x0: float, x1: float, y0: float, y1: float) -> None:
        b = self.box
        if b is None:
            self.box = [x0, x1, y0, y1]
        else:
            self.box = [min(b[0], x0), max(b[1], x1), min(b[2], y0), max(b[3], y1)]

    def framed(self, margin_m: float = 1.5) -> tuple[float, float, float, float] | None:
        """The box with a margin (m), or None when nothing was logged."""
        if self.box is None:
            return None
        x0, x1, y0, y1 = self.box
        return (x0 - margin_m, x1 + margin_m, y0 - margin_m, y1 + margin_m)


class Telemetry(Closing):
    """phalanx's entity layout over one recording id, to a file, a viewer, both, or memory.

    Every call only appends to a bounded `Outbox`, whose background thread hands entries
    to the Rerun SDK (at the lowest priority with `background`, for a process whose
    control loop must not wait for it); a viewer that goes away costs only its own
    entries (counted in `dropped`), and one that comes back is sent the static entities
    (obstacles, bounds, layout) again.
    """

    def __init__(
        self,
        *,
        recording_id: str,
        sink: TelemetrySink,
        app_id: str = "phalanx",
        robot_id: str | None = None,
        background: bool = False,
    ) -> None:
        self.sink = sink
        self.robot_id = robot_id
        self.app_id, self.recording_id = app_id, recording_id
        self.logged_steps: dict[str, int] = {}
        self._trails: dict[str, deque[tuple[float, float]]] = {}
        self._extent = _Extent()
        self._layout_ids: list[str] | None = None  # set once a layout was sent
        self._outbox = Outbox(
            recording_id=recording_id, sink=sink, app_id=app_id, background=background
        )

    @property
    def dropped(self) -> int:
        """Entries that missed at least one sink."""
        return self._outbox.dropped

    @property
    def viewer_live(self) -> bool:
        """Whether a viewer sink is connected now (False without one)."""
        return self._outbox.viewer_live

    # --- logging -----------------------------------------------------------------------

    def log_world(
        self,
        *,
        circles: Sequence[tuple[float, float, float]],
        polygons: Sequence[Sequence[tuple[float, float]]],
    ) -> None:
        """Static obstacle outlines."""
        strips = [_circle_outline(x, y, r) for x, y, r in circles]
        strips += [[*p, p[0]] for p in polygons if p]
        if not strips or not self._outbox.enabled:
            return
        arch = rerun_sdk().LineStrips2D(strips, colors=[(200, 200, 200)])
        self._outbox.submit(lambda rec: rec.log("world/obstacles", arch, static=True), static=True)

    def log_bounds(
        self,
        *,
        t_s: Sequence[float],
        linear_pct: float,
        angular_pct: float,
        v_max_mps: float,
        omega_max_radps: float,
    ) -> None:
        """The paper's error bounds and the velocity limits as flat series, sampled evenly
        from the first to the last of `t_s` (drawn as dotted lines).
        """
        series = {
            "bounds/errors/linear_pct": linear_pct,
            "bounds/errors/angular_pct": angular_pct,
            "bounds/velocity/v_max_mps": v_max_mps,
            "bounds/velocity/v_min_mps": -v_max_mps,
            "bounds/velocity/omega_max_degps": math.degrees(omega_max_radps),
            "bounds/velocity/omega_min_degps": -math.degrees(omega_max_radps),
        }
        given = np.asarray(t_s, dtype=np.float64)
        if given.size == 0:
            return
        times = np.linspace(given.min(), given.max(), BOUND_SAMPLES)
        for path, value in series.items():
            values = {"scalars": np.full(len(times), value)}
            self._columns(path, times, values, static=True, steps=False)

    def log_step(
        self,
        robot_id: str,
        *,
        t_s: float,
        step: int,
        pose: Pose2D,
        cmd: Twist2D,
        measured: Twist2D,
        tracking: Tracking | None = None,
        sonar: SonarParams | None = None,
        sonar_ranges_m: Sequence[float] = (),
        fsm_state: str = "",
        leader_id: str = "",
        cov: tuple[float, ...] = (),
    ) -> None:
        """One control step of one robot (live agents); sent in batches of steps.

        The sonar rays are drawn from the ring's geometry (`sonar`, the same for every
        step of a robot) and the step's ranges; those at the maximum range see nothing.
        `tracking`: the slot target and the errors of a step that tracks a leader, or
        what computes them. Only the values are kept here: the batch is turned into
        columns when it goes out, on the telemetry thread.
        """
        self.logged_steps[robot_id] = self.logged_steps.get(robot_id, 0) + 1
        if not self._outbox.enabled:
            return
        self._extent.add_point(pose.x_m, pose.y_m)
        trail = self._trails.setdefault(robot_id, deque(maxlen=TRAIL_POINTS))
        # The trail keeps every TRAIL_EVERY_STEPS-th position (a point a second at 10 Hz, up
        # to TRAIL_POINTS) and is redrawn as often: its cost stays flat however long the run.
        trail_points = None
        if step % TRAIL_EVERY_STEPS == 0:
            trail.append((pose.x_m, pose.y_m))
            trail_points = tuple(trail)
        row = StepRow(
            t_s, step, pose, cmd, measured, fsm_state, leader_id, tracking,
            sonar_ranges_m, trail_points, cov,
        )  # fmt: skip
        self._outbox.add_row(
            robot_id, row, lambda rec, rows: send_step_rows(rec, robot_id, rows, sonar)
        )

    def log_transition(
        self, robot_id: str, *, t_s: float, source: str, target: str, reason: str
    ) -> None:
        """A state-machine transition as a text log line."""
        text = f"t={t_s:.1f} s {robot_id}: {source} -> {target} ({reason})"

        def job(rec: Any) -> None:
            rr = rerun_sdk()
            rec.set_time("sim_time", duration=t_s)
            rec.log(f"robots/{robot_id}/fsm", rr.TextLog(text, level="INFO"))
            rec.log(f"robots/{robot_id}/state", rr.StateChange(state=target))

        self._outbox.submit(job)

    def log_truth(self, robot_id: str, *, t_s: float, pose: Pose2D) -> None:
        """Ground truth from the world; sent in batches of steps."""
        self._extent.add_point(pose.x_m, pose.y_m)
        self._outbox.add_row(
            f"truth/{robot_id}",
            TruthRow(t_s, pose.x_m, pose.y_m),
            lambda rec, rows: send_truth_rows(rec, robot_id, rows),
        )

    def log_columns(
        self,
        robot_id: str,
        *,
        t_s: FloatArray,
        x_m: FloatArray,
        y_m: FloatArray,
        theta_rad: FloatArray,
        cmd_v: FloatArray,
        cmd_omega: FloatArray,
        meas_v: FloatArray,
        meas_omega: FloatArray,
        linear_pct: FloatArray,
        angular_pct: FloatArray,
        orientation_deg: FloatArray,
    ) -> None:
        """A whole run of one robot at once (the batch runner), as columns."""
        self.logged_steps[robot_id] = self.logged_steps.get(robot_id, 0) + len(t_s)
        self._extent.add(x_m, y_m)
        base = f"robots/{robot_id}"
        pose = {"points": np.column_stack([x_m, y_m]), "radius": POSE_RADIUS_M, "label": robot_id}
        self._columns(f"{base}/pose", t_s, pose)
        heading = 0.4 * np.column_stack([np.cos(theta_rad), np.sin(theta_rad)])
        self._columns(f"{base}/heading", t_s, {"arrows": (heading, np.column_stack([x_m, y_m]))})
        scalars = {
            "cmd/v_mps": cmd_v,
            "cmd/omega_degps": np.degrees(cmd_omega),
            "measured/v_mps": meas_v,
            "measured/omega_degps": np.degrees(meas_omega),
            "errors/linear_pct": linear_pct,
            "errors/angular_pct": angular_pct,
            "errors/orientation_deg": orientation_deg,
        }
        for name, values in scalars.items():
            if np.all(np.isnan(values)):
                continue
            self._columns(f"{base}/{name}", t_s, {"scalars": values})
        trail = np.column_stack([x_m, y_m])
        self._outbox.submit(
            lambda rec: rec.log(f"{base}/trail", rerun_sdk().LineStrips2D([trail]), static=True)
        )

    def log_estimates(
        self,
        robot_id: str,
        *,
        t_s: FloatArray,
        estimate: FloatArray,
        cov: FloatArray,
        truth_xy: FloatArray,
    ) -> None:
        """A whole run's published poses (n x 3), their covariances (n x 6, NaN rows:
        none) and their error against the truth (n x 2), as columns (the batch runner).
        """
        if not self._outbox.enabled or not np.isfinite(cov).any():
            return
        base = f"robots/{robot_id}"
        every = TRAIL_EVERY_STEPS  # an ellipse a second is plenty on a whole run's map
        rows = range(0, len(t_s), every)
        strips = [ellipse(estimate[k, 0], estimate[k, 1], tuple(cov[k])) for k in rows]
        times = t_s[::every]

        def job(rec: Any) -> None:
            rr = rerun_sdk()
            index = [rr.TimeColumn("sim_time", duration=times)]
            send_ellipses(rec, rr, f"{base}/covariance", index, strips)

        self._outbox.submit(job)
        self._columns(f"{base}/estimate/xy", t_s, {"points": estimate[:, :2]})
        error = np.hypot(*(estimate[:, :2] - truth_xy).T)
        self._columns(f"{base}/estimate/error_m", t_s, {"scalars": error})
        stds = np.array([position_std_m(tuple(c)) for c in cov])
        self._columns(f"{base}/estimate/std_m", t_s, {"scalars": stds})

    def _columns(
        self,
        path: str,
        t_s: FloatArray,
        data: dict[str, Any],
        *,
        static: bool = False,
        steps: bool = True,
    ) -> None:
        def job(rec: Any) -> None:
            rr = rerun_sdk()
            times = [rr.TimeColumn("sim_time", duration=t_s)]
            if steps:  # the rows are a run's steps
                times.append(rr.TimeColumn("step", sequence=np.arange(len(t_s))))
            if "scalars" in data:
                columns = rr.Scalars.columns(scalars=data["scalars"])
            elif "points" in data:
                n = len(data["points"])
                extra = {}
                if "radius" in data:
                    extra = {"radii": np.full(n, data["radius"]), "labels": [data["label"]] * n}
                columns = rr.Points2D.columns(positions=data["points"], **extra)
            else:
                vectors, origins = data["arrows"]
                columns = rr.Arrows2D.columns(vectors=vectors, origins=origins)
            rec.send_columns(path, indexes=times, columns=columns)

        self._outbox.submit(job, static=static)

    def send_blueprint(
        self,
        robot_ids: Sequence[str] = (),
        *,
        extent_m: tuple[float, float, float, float] | None = None,
    ) -> None:
        """Send the layout (again, e.g. with the map framed on the whole run at its end)."""
        if not self._outbox.enabled:
            return
        self._layout_ids = list(robot_ids) or list(self.logged_steps)
        blueprint = make_blueprint(self._layout_ids, extent_m=extent_m)
        frame = map_frame_transform()  # the map view's y-up frame, before the view needs it
        self._outbox.submit(lambda rec: rec.log(MAP_FRAME_ENTITY, frame, static=True), static=True)
        self._outbox.submit(lambda rec: rec.send_blueprint(blueprint), static=True)

    # --- lifecycle ---------------------------------------------------------------------

    def flush(self, timeout_s: float = 0.0) -> bool:
        """Hand every buffered row over now; with a timeout, wait (bounded) until the
        background thread has passed everything to the sinks and they have it (written,
        or sent to the viewer). Whether they have.

        For a figure that must be complete at a given moment (`dropped` in a final report).
        """
        self._outbox.flush_rows()
        return self._outbox.wait(timeout_s)

    def close(self) -> None:
        """Drain what is queued (bounded), flush and finalize every sink; safe twice."""
        if self._outbox.closed:
            return
        self._outbox.flush_rows()
        extent = self._extent.framed()
        if self._layout_ids is not None and extent is not None:
            self.send_blueprint(self._layout_ids, extent_m=extent)  # the whole run in view
        self._outbox.close()


def _circle_outline(x: float, y: float, r: float, n: int = 32) -> list[tuple[float, float]]:
    return [
        (x + r * math.cos(2 * math.pi * k / n), y + r * math.sin(2 * math.pi * k / n))
        for k in range(n + 1)
    ]
