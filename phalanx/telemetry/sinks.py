"""Telemetry sinks: where entries go (an .rrd file, a Rerun viewer over gRPC, both, or
memory) and the background thread that hands them to the Rerun SDK.

Logging never blocks a control step: calls append to a bounded outbox drained by a
background thread (beside a control loop, at the lowest priority, so that its work fills
the time the control steps leave); when the sink is slow the oldest entries are dropped,
when a viewer is gone its entries are, and both are counted in `dropped`.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import shutil
import socket
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlparse

from pydantic import BaseModel, ConfigDict

Job = Callable[[Any], None]  # logs to a recording stream
log = logging.getLogger("phalanx.telemetry")
OUTBOX_CAPACITY = 20_000  # jobs; a job is one entry, or one batch of rows
FLUSH_ROWS = 100  # a robot's steps go out in batches of at most this many ...
FLUSH_S = 0.2  # ... and at most this old (wall time), so a live view lags by no more
CLOSE_TIMEOUT_S = 10.0
VIEWER_FLUSH_S = 2.0
VIEWER_CHECK_S = 1.0
DEFAULT_URL = "rerun+http://127.0.0.1:9876/proxy"
TELEMETRY_NICE = 19  # the telemetry thread's priority: the lowest a thread may have


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


def rerun_sdk() -> Any:
    """The Rerun SDK module (heavy: imported only when telemetry is on)."""
    import rerun

    return rerun


def viewer_reachable(url: str, timeout_s: float = 0.2) -> bool:
    """Whether something listens at a Rerun gRPC url's host and port (a TCP connect)."""
    parsed = urlparse(url)
    try:
        with socket.create_connection((parsed.hostname or "127.0.0.1", parsed.port or 9876),
                                      timeout=timeout_s):  # fmt: skip
            return True
    except OSError:
        return False


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


@dataclass
class _Batch:
    """Rows of one robot waiting to go out together, and how to send them."""

    send: Callable[[Any, list[Any]], None]
    rows: list[Any] = field(default_factory=list)
    started_s: float = field(default_factory=time.monotonic)


class Outbox:
    """The bounded queue between logging calls and the sinks, drained by its own thread.

    `background`: the thread runs at the lowest priority (beside a control loop, whose
    steps must not wait for it). Not for a recording written after a run, which nothing
    waits for but its end: a low-priority thread on a busy host could not finish it
    within `CLOSE_TIMEOUT_S`.

    A viewer is probed every `VIEWER_CHECK_S`: while it is gone its entries are dropped
    (counted), and when it comes back the stream reconnects and re-sends the static jobs
    (obstacles, bounds, layout). A file sink is a stream of its own, so a viewer coming
    and going never costs the recording anything.
    """

    def __init__(
        self, *, recording_id: str, sink: TelemetrySink, app_id: str, background: bool = False
    ) -> None:
        self.app_id, self.recording_id = app_id, recording_id
        self.background = background  # the thread yields to the process's control loop
        self.dropped = 0  # entries that missed at least one sink
        self.closed = False
        self._jobs: deque[tuple[Job, int]] = deque()  # (job, entries it carries)
        self._rows: dict[str, _Batch] = {}  # per robot (and per truth), not yet submitted
        self._static: list[Job] = []
        self._wake = threading.Condition()
        self._busy = False  # the background thread is applying a job
        self._streams = self._plan_streams(sink)
        self._worker: threading.Thread | None = None
        for stream in self._streams:
            if stream.kind != "grpc":  # a viewer connects from the worker: never blocks here
                self._start(stream)
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

    def _start(self, stream: _Stream) -> None:
        """Open a file (or memory) sink. One that cannot be opened (a full disk, a folder
        that cannot be made) is left out, said once, and its entries counted in `dropped`:
        a robot keeps driving without its recording rather than stop on it.
        """
        try:
            self._open(stream)
        except (OSError, RuntimeError) as exc:  # RuntimeError: the SDK's failed first write
            log.error(
                "telemetry: could not open the %s sink %s: %s", stream.kind, stream.target, exc
            )
            stream.rec = None

    def _open(self, stream: _Stream) -> None:
        rec = rerun_sdk().RecordingStream(
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
    def enabled(self) -> bool:
        """Whether there is any sink at all (False for an `off` sink)."""
        return bool(self._streams)

    @property
    def viewer_live(self) -> bool:
        """Whether a viewer sink is connected now (False without one)."""
        return any(s.live for s in self._streams if s.kind == "grpc")

    # --- the caller's side ---------------------------------------------------------------

    def submit(self, job: Job, *, static: bool = False, entries: int = 1) -> None:
        """Queue `job`; a static one is also kept, to re-send to a viewer that comes back."""
        if not self._streams or self.closed:
            return
        with self._wake:
            if static:
                self._static.append(job)
            if len(self._jobs) >= OUTBOX_CAPACITY:
                _, lost = self._jobs.popleft()
                self.dropped += lost
            self._jobs.append((job, entries))
            self._wake.notify()

    def add_row(self, key: str, row: object, send: Callable[[Any, list[Any]], None]) -> None:
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
            self.submit(lambda rec: send(rec, rows), entries=len(rows))

    def flush_rows(self) -> None:
        """Hand every buffered batch of rows over now."""
        with self._wake:
            for key in list(self._rows):
                self._flush(key)

    def wait(self, timeout_s: float) -> bool:
        """Wait (bounded) until the background thread has passed everything to the sinks,
        and the SDK has sent or written it. Whether it has.
        """
        deadline = time.monotonic() + timeout_s
        while self._jobs or self._busy:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        for stream in self._streams:
            rec, left_s = stream.rec, deadline - time.monotonic()
            if rec is None:
                continue
            if left_s <= 0.0:
                return False
            try:
                rec.flush(timeout_sec=left_s)
            except RuntimeError as exc:  # the SDK's timeout, or a viewer that went away
                log.info("telemetry: the %s sink did not take everything yet: %s", stream.kind, exc)
                return False
        return True

    def close(self) -> None:
        """Drain what is queued (bounded), then flush and finalize every sink; safe twice."""
        if self.closed:
            return
        with self._wake:
            self.closed = True
            self._wake.notify_all()
        if self._worker is not None:
            self._worker.join(CLOSE_TIMEOUT_S)
        with self._wake:
            self.dropped += len(self._jobs)
            self._jobs.clear()
        for stream in self._streams:
            self._finish(stream)

    # --- the background thread -----------------------------------------------------------

    def _drain(self) -> None:
        if self.background:
            _yield_to_control()
        while True:
            with self._wake:
                if not self._jobs and not self.closed:
                    self._wake.wait(VIEWER_CHECK_S)
                if not self._jobs and self.closed:
                    return
                job = self._jobs.popleft() if self._jobs else None
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
            if stream.kind != "grpc" or now < stream.next_check_s or self.closed:
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


def _yield_to_control() -> None:
    """Run the calling (telemetry) thread at the lowest priority (Linux: a thread has its
    own nice value): turning rows into columns takes a few milliseconds a batch, which
    must come out of the time a control step leaves, not delay the next step of this
    process or of another on the same CPU. Elsewhere, or when refused, it runs as it is.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), TELEMETRY_NICE)
    except OSError as exc:
        log.info("telemetry: could not lower the telemetry thread's priority: %s", exc)
