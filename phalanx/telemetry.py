"""Rerun telemetry: one recording per fleet run, shared by every process by its id.

Entity layout (units and frames in the names):
    world/obstacles                      static outlines
    world/truth/<id>                     ground-truth position (the world process)
    robots/<id>/pose, /heading, /trail   where the robot believes it is
    robots/<id>/slot_target              the rigid-body target it tracks
    robots/<id>/sonar                    sonar rays in the world frame
    robots/<id>/cmd/{v_mps,omega_degps}  commanded twist
    robots/<id>/measured/{v_mps,omega_degps}
    robots/<id>/errors/{linear_pct,angular_pct,orientation_deg}
    robots/<id>/fsm                      state transitions (text log)
    bounds/...                           the paper's error bounds and the velocity limits
Timelines: `sim_time` (s) and `step`.

Logging never blocks a control step: calls append to a bounded outbox drained by a
background thread; when the sink is slow or gone the oldest entries are dropped and
counted in `dropped`.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, Literal, Self

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict

from phalanx.config import RobotParams
from phalanx.geometry import Pose2D, Twist2D, Vec2

FloatArray = npt.NDArray[np.float64]
OUTBOX_CAPACITY = 20_000
TRAIL_POINTS = 600
TRAIL_EVERY_STEPS = 10
CLOSE_TIMEOUT_S = 10.0
DEFAULT_URL = "rerun+http://127.0.0.1:9876/proxy"
# Section 5 of the paper: backward-motion errors below 2 % linear and 0.8 % angular.
PAPER_LINEAR_BOUND_PCT = 2.0
PAPER_ANGULAR_BOUND_PCT = 0.8


class TelemetrySink(BaseModel):
    """Where telemetry goes: nowhere, an .rrd file, a gRPC viewer/aggregator, or memory."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: Literal["off", "file", "grpc", "tee", "memory"] = "off"  # tee: file and grpc
    path: Path | None = None
    url: str | None = None


def sink_for(path: Path | None, url: str | None) -> TelemetrySink:
    """A file sink, a gRPC (viewer) sink, both, or off, from what is given."""
    if path is not None and url is not None:
        return TelemetrySink(kind="tee", path=path, url=url)
    if path is not None:
        return TelemetrySink(kind="file", path=path)
    if url is not None:
        return TelemetrySink(kind="grpc", url=url)
    return TelemetrySink(kind="off")


def _rr() -> Any:
    import rerun  # heavy: imported only when telemetry is on

    return rerun


def make_blueprint(
    robot_ids: Sequence[str],
    *,
    linear_bound_pct: float = 2.0,
    angular_bound_pct: float = 0.8,
) -> Any:
    """Map of the fleet, error and velocity series, state log: figures 4b-7 live."""
    import rerun.blueprint as rrb

    del linear_bound_pct, angular_bound_pct  # drawn as bounds/* series by the logger
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(name="fleet map", origin="/"),
            rrb.Vertical(
                rrb.TimeSeriesView(
                    name="separation errors",
                    origin="/",
                    contents=["robots/*/errors/**", "bounds/errors/**"],
                ),
                rrb.TimeSeriesView(
                    name="velocities",
                    origin="/",
                    contents=["robots/*/cmd/**", "robots/*/measured/**", "bounds/velocity/**"],
                ),
                rrb.TextLogView(name="state machine", origin="/", contents=["robots/*/fsm"]),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


class Telemetry:
    """A recording stream with phalanx's entity layout; context manager."""

    def __init__(
        self,
        *,
        recording_id: str,
        sink: TelemetrySink,
        app_id: str = "phalanx",
        robot_id: str | None = None,
    ) -> None:
        self.sink = sink
        self.robot_id = robot_id
        self.dropped = 0
        self.logged_steps: dict[str, int] = {}
        self._trails: dict[str, deque[tuple[float, float]]] = {}
        self._outbox: deque[Callable[[], None]] = deque()
        self._wake = threading.Condition()
        self._closed = False
        self._rec: Any = None
        self._worker: threading.Thread | None = None
        if sink.kind != "off":
            self._rec = self._open(app_id, recording_id)
            self._worker = threading.Thread(target=self._drain, name="telemetry", daemon=True)
            self._worker.start()

    def _open(self, app_id: str, recording_id: str) -> Any:
        rr = _rr()
        rec = rr.RecordingStream(app_id, recording_id=recording_id, send_properties=False)
        if self.sink.kind == "file":
            if self.sink.path is None:
                raise ValueError("a file sink needs a path")
            self.sink.path.parent.mkdir(parents=True, exist_ok=True)
            rec.save(str(self.sink.path))
        elif self.sink.kind == "grpc":
            rec.connect_grpc(self.sink.url or DEFAULT_URL)
        elif self.sink.kind == "tee":
            if self.sink.path is None:
                raise ValueError("a tee sink needs a path")
            self.sink.path.parent.mkdir(parents=True, exist_ok=True)
            rec.set_sinks(
                rr.FileSink(str(self.sink.path)), rr.GrpcSink(self.sink.url or DEFAULT_URL)
            )
        else:
            rec.memory_recording()
        return rec

    # --- outbox ------------------------------------------------------------------------

    def _submit(self, job: Callable[[], None]) -> None:
        if self._rec is None or self._closed:
            return
        with self._wake:
            if len(self._outbox) >= OUTBOX_CAPACITY:
                self._outbox.popleft()
                self.dropped += 1
            self._outbox.append(job)
            self._wake.notify()

    def _drain(self) -> None:
        while True:
            with self._wake:
                while not self._outbox and not self._closed:
                    self._wake.wait(0.5)
                if not self._outbox and self._closed:
                    return
                job = self._outbox.popleft()
            job()

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
        rr = _rr()
        arch = rr.LineStrips2D(strips, colors=[(200, 200, 200)]) if strips else None
        if arch is not None:
            self._submit(lambda: self._rec.log("world/obstacles", arch, static=True))

    def log_bounds(
        self,
        *,
        t_s: Sequence[float],
        linear_pct: float,
        angular_pct: float,
        v_max_mps: float,
        omega_max_radps: float,
    ) -> None:
        """The paper's error bounds and the velocity limits as flat series."""
        series = {
            "bounds/errors/linear_pct": linear_pct,
            "bounds/errors/angular_pct": angular_pct,
            "bounds/velocity/v_max_mps": v_max_mps,
            "bounds/velocity/omega_max_degps": math.degrees(omega_max_radps),
        }
        times = np.asarray(t_s, dtype=np.float64)
        for path, value in series.items():
            self._columns(path, times, {"scalars": np.full(len(times), value)})

    def log_step(
        self,
        robot_id: str,
        *,
        t_s: float,
        step: int,
        pose: Pose2D,
        cmd: Twist2D,
        measured: Twist2D,
        slot_target: Pose2D | None = None,
        errors: tuple[float, float, float] | None = None,
        sonar_rays: Sequence[tuple[Vec2, Vec2]] = (),
        fsm_state: str = "",
        leader_id: str = "",
    ) -> None:
        """One control step of one robot (live agents)."""
        self.logged_steps[robot_id] = self.logged_steps.get(robot_id, 0) + 1
        if self._rec is None:
            return
        trail = self._trails.setdefault(robot_id, deque(maxlen=TRAIL_POINTS))
        trail.append((pose.x_m, pose.y_m))
        # The trail (the last minute of positions) is redrawn once a second, not every step.
        trail_points = list(trail) if step % TRAIL_EVERY_STEPS == 0 else None
        rays = [[(a.x_m, a.y_m), (b.x_m, b.y_m)] for a, b in sonar_rays]
        label = f"{robot_id} {fsm_state}" + (f" -> {leader_id}" if leader_id else "")

        def job() -> None:
            rr, rec, base = _rr(), self._rec, f"robots/{robot_id}"
            rec.set_time("sim_time", duration=t_s)
            rec.set_time("step", sequence=step)
            rec.log(
                f"{base}/pose",
                rr.Points2D([(pose.x_m, pose.y_m)], radii=0.25, labels=[label]),
            )
            heading = (0.4 * math.cos(pose.theta_rad), 0.4 * math.sin(pose.theta_rad))
            rec.log(
                f"{base}/heading", rr.Arrows2D(vectors=[heading], origins=[(pose.x_m, pose.y_m)])
            )
            if trail_points is not None:
                rec.log(f"{base}/trail", rr.LineStrips2D([trail_points]))
            if slot_target is not None:
                rec.log(
                    f"{base}/slot_target",
                    rr.Points2D([(slot_target.x_m, slot_target.y_m)], radii=0.05),
                )
            if rays:
                rec.log(f"{base}/sonar", rr.LineStrips2D(rays, radii=0.005))
            self._log_scalars(base, cmd, measured, errors)

        self._submit(job)

    def _log_scalars(
        self, base: str, cmd: Twist2D, measured: Twist2D, errors: tuple[float, float, float] | None
    ) -> None:
        rr, rec = _rr(), self._rec
        rec.log(f"{base}/cmd/v_mps", rr.Scalars(cmd.v_mps))
        rec.log(f"{base}/cmd/omega_degps", rr.Scalars(math.degrees(cmd.omega_radps)))
        rec.log(f"{base}/measured/v_mps", rr.Scalars(measured.v_mps))
        rec.log(f"{base}/measured/omega_degps", rr.Scalars(math.degrees(measured.omega_radps)))
        if errors is not None:
            for name, value in zip(
                ("linear_pct", "angular_pct", "orientation_deg"), errors, strict=True
            ):
                rec.log(f"{base}/errors/{name}", rr.Scalars(value))

    def log_transition(
        self, robot_id: str, *, t_s: float, source: str, target: str, reason: str
    ) -> None:
        """A state-machine transition as a text log line."""

        def job() -> None:
            rr = _rr()
            self._rec.set_time("sim_time", duration=t_s)
            text = f"t={t_s:.1f} s {robot_id}: {source} -> {target} ({reason})"
            self._rec.log(f"robots/{robot_id}/fsm", rr.TextLog(text, level="INFO"))

        self._submit(job)

    def log_truth(self, robot_id: str, *, t_s: float, pose: Pose2D) -> None:
        """Ground truth from the world."""

        def job() -> None:
            rr = _rr()
            self._rec.set_time("sim_time", duration=t_s)
            self._rec.log(
                f"world/truth/{robot_id}",
                rr.Points2D([(pose.x_m, pose.y_m)], radii=0.05, colors=[(0, 0, 0)]),
            )

        self._submit(job)

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
        base = f"robots/{robot_id}"
        self._columns(f"{base}/pose", t_s, {"points": np.column_stack([x_m, y_m])})
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
        self._submit(
            lambda: self._rec.log(f"{base}/trail", _rr().LineStrips2D([trail]), static=True)
        )

    def _columns(self, path: str, t_s: FloatArray, data: dict[str, Any]) -> None:
        def job() -> None:
            rr = _rr()
            times = [
                rr.TimeColumn("sim_time", duration=t_s),
                rr.TimeColumn("step", sequence=np.arange(len(t_s))),
            ]
            if "scalars" in data:
                columns = rr.Scalars.columns(scalars=data["scalars"])
            elif "points" in data:
                columns = rr.Points2D.columns(positions=data["points"])
            else:
                vectors, origins = data["arrows"]
                columns = rr.Arrows2D.columns(vectors=vectors, origins=origins)
            self._rec.send_columns(path, indexes=times, columns=columns)

        self._submit(job)

    def send_blueprint(self, robot_ids: Sequence[str] = ()) -> None:
        """Send the default layout."""
        ids = list(robot_ids) or list(self.logged_steps)
        self._submit(lambda: self._rec.send_blueprint(make_blueprint(ids)))

    # --- lifecycle ---------------------------------------------------------------------

    def close(self) -> None:
        """Drain what is queued (bounded), flush and finalize the sink; safe twice."""
        if self._closed:
            return
        with self._wake:
            self._closed = True
            self._wake.notify_all()
        if self._worker is not None:
            self._worker.join(CLOSE_TIMEOUT_S)
            self.dropped += len(self._outbox)
        if self._rec is not None:
            self._rec.flush(timeout_sec=CLOSE_TIMEOUT_S)
            if self.sink.kind in ("file", "tee"):
                self._rec.disconnect()  # finalizes the .rrd footer

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def sonar_rays(
    robot: RobotParams, pose: Pose2D, ranges_m: Sequence[float]
) -> list[tuple[Vec2, Vec2]]:
    """World-frame segments of the sonars that see something (range below the maximum)."""
    rays = []
    for unit, range_m in zip(robot.sonar.units, ranges_m, strict=False):
        if range_m >= robot.sonar.max_range_m:
            continue
        start = pose.to_world(Vec2(unit.x_m, unit.y_m))
        heading = pose.theta_rad + math.radians(unit.heading_deg)
        end = start + Vec2(range_m * math.cos(heading), range_m * math.sin(heading))
        rays.append((start, end))
    return rays


def _circle_outline(x: float, y: float, r: float, n: int = 32) -> list[tuple[float, float]]:
    return [
        (x + r * math.cos(2 * math.pi * k / n), y + r * math.sin(2 * math.pi * k / n))
        for k in range(n + 1)
    ]
