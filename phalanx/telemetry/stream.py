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
    robots/<id>/state                    behaviour state over time (the paper's figure 4b)
    bounds/...                           the paper's error bounds and the velocity limits
Timelines: `sim_time` (s) and `step`.

Logging never blocks a control step: calls append to a bounded outbox drained by a
background thread; when the sink is slow the oldest entries are dropped, when a viewer
is gone its entries are, and both are counted in `dropped`.
"""

from __future__ import annotations

import importlib.util
import logging
import math
import shutil
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlparse

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict

from phalanx.core.config import RobotParams
from phalanx.core.geometry import Pose2D, Twist2D, Vec2
from phalanx.core.lifecycle import Closing
from phalanx.telemetry.layout import (
    StepRow,
    TruthRow,
    make_blueprint,
    send_step_rows,
    send_truth_rows,
)

FloatArray = npt.NDArray[np.float64]
Job = Callable[[Any], None]  # logs to a recording stream
log = logging.getLogger("phalanx.telemetry")
OUTBOX_CAPACITY = 20_000  # jobs; a job is one entry, or one batch of rows
FLUSH_ROWS = 20  # a robot's steps go out in batches of at most this many ...
FLUSH_S = 0.2  # ... and at most this old (wall time), so a live view lags by no more
TRAIL_POINTS = 600
TRAIL_EVERY_STEPS = 10
CLOSE_TIMEOUT_S = 10.0
VIEWER_FLUSH_S = 2.0
VIEWER_CHECK_S = 1.0
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


def rerun_executable() -> str:
    """The Rerun CLI binary itself.

    The `rerun` on PATH is a Python wrapper that runs the binary as a child: a SIGTERM to
    the wrapper would orphan the binary (a viewer or merge left running), so phalanx
    starts and stops the binary directly.
    """
    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.origin is not None:
        binary = Path(spec.origin).with_name("rerun")
        if binary.is_file():
            return str(binary)
    return shutil.which("rerun") or "rerun"


def _rr() -> Any:
    import rerun  # heavy: imported only when telemetry is on

    return rerun


class _Extent:
    """The bounding box of every position logged, to frame the map at the end of a run."""

    def __init__(self) -> None:
        self.box: list[float] | None = None  # x_min, x_max, y_min, y_max

    def add(self, x_m: FloatArray | float, y_m: FloatArray | float) -> None:
        """Grow the box to include the given positions."""
        xs, ys = np.atleast_1d(x_m), np.atleast_1d(y_m)
        if xs.size == 0:
            return
        new = [float(xs.min()), float(xs.max()), float(ys.min()), float(ys.max())]
        if self.box is None:
            self.box = new
            return
        b = self.box
        self.box = [min(b[0], new[0]), max(b[1], new[1]), min(b[2], new[2]), max(b[3], new[3])]

    def framed(self, margin_m: float = 1.5) -> tuple[float, float, float, float] | None:
        """The box with a margin (m), or None when nothing was logged."""
        if self.box is None:
            return None
        x0, x1, y0, y1 = self.box
        return (x0 - margin_m, x1 + margin_m, y0 - margin_m, y1 + margin_m)


class _Stream:
    """One sink's recording stream. A viewer (gRPC) stream can go down and come back."""

    def __init__(self, kind: Literal["file", "grpc", "memory"], target: str | None) -> None:
        self.kind, self.target = kind, target
        self.rec: Any = None
        self.next_check_s = 0.0

    @property
    def live(self) -> bool:
        """Whether entries reach this sink now."""
        return self.rec is not None


def viewer_reachable(url: str, timeout_s: float = 0.2) -> bool:
    """Whether something listens at a Rerun gRPC url's host and port (a TCP connect)."""
    parsed = urlparse(url)
    try:
        with socket.create_connection((parsed.hostname or "127.0.0.1", parsed.port or 9876),
                                      timeout=timeout_s):  # fmt: skip
            return True
    except OSError:
        return False


@dataclass
class _Batch:
    """Rows of one robot waiting to go out together, and how to send them."""

    send: Callable[[Any, list[Any]], None]
    rows: list[Any] = field(default_factory=list)
    started_s: float = field(default_factory=time.monotonic)


class Telemetry(Closing):
    """phalanx's entity layout over one recording id, to a file, a viewer, both, or memory.

    Every call only appends to a bounded outbox; a background thread hands entries to the
    Rerun SDK. A viewer is probed every `VIEWER_CHECK_S`: while it is gone its entries
    are dropped (counted), and when it comes back the stream reconnects and re-sends the
    static entities (obstacles, bounds, layout). A file sink is a stream of its own, so a
    viewer coming and going never costs the recording anything.
    """

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
        self.app_id, self.recording_id = app_id, recording_id
        self.dropped = 0  # entries that missed at least one sink
        self.logged_steps: dict[str, int] = {}
        self._trails: dict[str, deque[tuple[float, float]]] = {}
        self._outbox: deque[tuple[Job, int]] = deque()  # (job, entries it carries)
        self._rows: dict[str, _Batch] = {}  # per robot (and per truth), not yet submitted
        self._static: list[Job] = []
        self._extent = _Extent()
        self._layout_ids: list[str] | None = None  # set once a layout was sent
        self._wake = threading.Condition()
        self._busy = False  # the background thread is applying a job
        self._closed = False
        self._streams = self._plan_streams(sink)
        self._worker: threading.Thread | None = None
        for stream in self._streams:
            if stream.kind != "grpc":  # a viewer connects from the worker: never blocks here
                self._open(stream)
        if self._streams:
            self._worker = threading.Thread(target=self._drain, name="telemetry", daemon=True)
            self._worker.start()

    @staticmethod
    def _plan_streams(sink: TelemetrySink) -> list[_Stream]:
        if sink.kind in ("file", "tee") and sink.path is None:
            raise ValueError(f"a {sink.kind} sink needs a path")
        streams = []
        if sink.kind in ("file", "tee"):
            streams.append(_Stream("file", str(sink.path)))
        if sink.kind in ("grpc", "tee"):
            streams.append(_Stream("grpc", sink.url or DEFAULT_URL))
        if sink.kind == "memory":
            streams.append(_Stream("memory", None))
        return streams

    def _open(self, stream: _Stream) -> None:
        rec = _rr().RecordingStream(
            self.app_id, recording_id=self.recording_id, send_properties=False
        )
        if stream.kind == "file":
            path = Path(stream.target or "")
            path.parent.mkdir(parents=True, exist_ok=True)
            rec.save(str(path))
        elif stream.kind == "grpc":
            rec.connect_grpc(stream.target)
        else:
            rec.memory_recording()
        stream.rec = rec

    @property
    def viewer_live(self) -> bool:
        """Whether a viewer sink is connected now (False without one)."""
        return any(s.live for s in self._streams if s.kind == "grpc")

    # --- outbox ------------------------------------------------------------------------

    def _submit(self, job: Job, *, static: bool = False, entries: int = 1) -> None:
        if not self._streams or self._closed:
            return
        with self._wake:
            if static:
                self._static.append(job)
            if len(self._outbox) >= OUTBOX_CAPACITY:
                _, lost = self._outbox.popleft()
                self.dropped += lost
            self._outbox.append((job, entries))
            self._wake.notify()

    def _add_row(self, key: str, row: object, send: Callable[[Any, list[Any]], None]) -> None:
        """Buffer `row`; hand the batch over when it is full or old enough."""
        with self._wake:
            batch = self._rows.get(key)
            if batch is None:
                batch = self._rows[key] = _Batch(send)
            batch.rows.append(row)
            if len(batch.rows) >= FLUSH_ROWS or time.monotonic() - batch.started_s >= FLUSH_S:
                self._flush(key)

    def _flush(self, key: str) -> None:
        batch = self._rows.pop(key, None)
        if batch is not None and batch.rows:
            rows, send = batch.rows, batch.send
            self._submit(lambda rec: send(rec, rows), entries=len(rows))

    def _drain(self) -> None:
        while True:
            with self._wake:
                if not self._outbox and not self._closed:
                    self._wake.wait(VIEWER_CHECK_S)
                if not self._outbox and self._closed:
                    return
                job = self._outbox.popleft() if self._outbox else None
                self._busy = job is not None
            self._check_viewers()
            if job is not None:
                self._apply(*job)
            self._busy = False

    def _apply(self, job: Job, entries: int) -> None:
        missed = False
        for stream in self._streams:
            if not stream.live:
                missed = True
                continue
            try:
                job(stream.rec)
            except Exception:  # a sink's failure must not end telemetry (or the robot)
                log.exception("telemetry: logging to the %s sink failed", stream.kind)
                missed = True
        if missed:
            with self._wake:
                self.dropped += entries

    def _check_viewers(self) -> None:
        now = time.monotonic()
        for stream in self._streams:
            if stream.kind != "grpc" or now < stream.next_check_s or self._closed:
                continue
            stream.next_check_s = now + VIEWER_CHECK_S
            reachable = viewer_reachable(stream.target or DEFAULT_URL)
            if stream.live and not reachable:
                log.warning("telemetry: viewer at %s is gone; dropping live data", stream.target)
                stream.rec = None
            elif not stream.live and reachable:
                self._reconnect(stream)

    def _reconnect(self, stream: _Stream) -> None:
        try:
            self._open(stream)
            for job in list(self._static):
                job(stream.rec)
        except Exception:
            log.exception("telemetry: could not connect to the viewer at %s", stream.target)
            stream.rec = None
            return
        log.info("telemetry: streaming to the viewer at %s", stream.target)

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
        if not strips or not self._streams:
            return
        arch = _rr().LineStrips2D(strips, colors=[(200, 200, 200)])
        self._submit(lambda rec: rec.log("world/obstacles", arch, static=True), static=True)

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
            "bounds/velocity/v_min_mps": -v_max_mps,
            "bounds/velocity/omega_max_degps": math.degrees(omega_max_radps),
            "bounds/velocity/omega_min_degps": -math.degrees(omega_max_radps),
        }
        times = np.asarray(t_s, dtype=np.float64)
        for path, value in series.items():
            self._columns(path, times, {"scalars": np.full(len(times), value)}, static=True)

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
        """One control step of one robot (live agents); sent in batches of steps."""
        self.logged_steps[robot_id] = self.logged_steps.get(robot_id, 0) + 1
        if not self._streams:
            return
        self._extent.add(pose.x_m, pose.y_m)
        trail = self._trails.setdefault(robot_id, deque(maxlen=TRAIL_POINTS))
        # The trail keeps every TRAIL_EVERY_STEPS-th position (a point a second at 10 Hz, up
        # to TRAIL_POINTS) and is redrawn as often: its cost stays flat however long the run.
        trail_points = None
        if step % TRAIL_EVERY_STEPS == 0:
            trail.append((pose.x_m, pose.y_m))
            trail_points = tuple(trail)
        row = StepRow(
            t_s=t_s,
            step=step,
            pose=pose,
            cmd=cmd,
            measured=measured,
            label=f"{robot_id} {fsm_state}" + (f" -> {leader_id}" if leader_id else ""),
            slot_target=slot_target,
            errors=errors,
            rays=tuple(((a.x_m, a.y_m), (b.x_m, b.y_m)) for a, b in sonar_rays),
            trail=trail_points,
        )
        self._add_row(robot_id, row, lambda rec, rows: send_step_rows(rec, robot_id, rows))

    def log_transition(
        self, robot_id: str, *, t_s: float, source: str, target: str, reason: str
    ) -> None:
        """A state-machine transition as a text log line."""
        text = f"t={t_s:.1f} s {robot_id}: {source} -> {target} ({reason})"

        def job(rec: Any) -> None:
            rr = _rr()
            rec.set_time("sim_time", duration=t_s)
            rec.log(f"robots/{robot_id}/fsm", rr.TextLog(text, level="INFO"))
            rec.log(f"robots/{robot_id}/state", rr.StateChange(state=target))

        self._submit(job)

    def log_truth(self, robot_id: str, *, t_s: float, pose: Pose2D) -> None:
        """Ground truth from the world; sent in batches of steps."""
        self._extent.add(pose.x_m, pose.y_m)
        self._add_row(
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
        self._submit(lambda rec: rec.log(f"{base}/trail", _rr().LineStrips2D([trail]), static=True))

    def _columns(
        self, path: str, t_s: FloatArray, data: dict[str, Any], *, static: bool = False
    ) -> None:
        def job(rec: Any) -> None:
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
            rec.send_columns(path, indexes=times, columns=columns)

        self._submit(job, static=static)

    def send_blueprint(
        self,
        robot_ids: Sequence[str] = (),
        *,
        extent_m: tuple[float, float, float, float] | None = None,
    ) -> None:
        """Send the layout (again, e.g. with the map framed on the whole run at its end)."""
        if not self._streams:
            return
        self._layout_ids = list(robot_ids) or list(self.logged_steps)
        blueprint = make_blueprint(self._layout_ids, extent_m=extent_m)
        self._submit(lambda rec: rec.send_blueprint(blueprint), static=True)

    # --- lifecycle ---------------------------------------------------------------------

    def flush(self, timeout_s: float = 0.0) -> bool:
        """Hand every buffered row over now; with a timeout, wait (bounded) until the
        background thread has passed everything to the sinks. Whether it has.

        For a figure that must be complete at a given moment (`dropped` in a final report).
        """
        with self._wake:
            for key in list(self._rows):
                self._flush(key)
        deadline = time.monotonic() + timeout_s
        while self._outbox or self._busy:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return True

    def close(self) -> None:
        """Drain what is queued (bounded), flush and finalize every sink; safe twice."""
        if self._closed:
            return
        with self._wake:
            for key in list(self._rows):
                self._flush(key)
        extent = self._extent.framed()
        if self._layout_ids is not None and extent is not None:
            self.send_blueprint(self._layout_ids, extent_m=extent)  # the whole run in view
        with self._wake:
            self._closed = True
            self._wake.notify_all()
        if self._worker is not None:
            self._worker.join(CLOSE_TIMEOUT_S)
        with self._wake:
            self.dropped += len(self._outbox)
            self._outbox.clear()
        for stream in self._streams:
            self._finish(stream)

    @staticmethod
    def _finish(stream: _Stream) -> None:
        if stream.rec is None:
            return
        # A viewer that went away makes the SDK's flush fail: that must not fail the caller.
        timeout_s = CLOSE_TIMEOUT_S if stream.kind == "file" else VIEWER_FLUSH_S
        try:
            stream.rec.flush(timeout_sec=timeout_s)
        except RuntimeError as exc:
            log.warning("telemetry: the %s sink did not take everything: %s", stream.kind, exc)
        if stream.kind == "file":
            stream.rec.disconnect()  # finalizes the .rrd footer
        stream.rec = None


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
