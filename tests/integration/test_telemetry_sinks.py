"""Telemetry against a real Rerun gRPC server (`rerun --serve-grpc --save`, the headless
aggregator): a viewer that is absent, goes away, or comes back never blocks or fails the
caller; what it misses is counted; a file sink beside it keeps everything."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.rigid_body import LiveErrors
from phalanx.telemetry.rrd import summarize
from phalanx.telemetry.sinks import TelemetrySink, rerun_executable, viewer_reachable
from phalanx.telemetry.stream import Telemetry
from phalanx.wire.transport import free_tcp_port

pytestmark = [
    pytest.mark.integration,
    pytest.mark.filterwarnings("ignore:RRD file has no footer"),  # the aggregator's own file
]
RERUN = rerun_executable()


@contextmanager
def aggregator(port: int, path: Path) -> Iterator[None]:
    """A headless Rerun gRPC server saving what it receives; stopped with Ctrl-C."""
    proc = subprocess.Popen(
        [
            str(RERUN),
            "--serve-grpc",
            "--bind",
            "127.0.0.1",
            "--port",
            str(port),
            "--save",
            str(path),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        wait_for(lambda: viewer_reachable(f"rerun+http://127.0.0.1:{port}/proxy"), 15.0)
        yield
    finally:
        stop(proc, signal.SIGINT)


def stop(proc: subprocess.Popen[bytes], sig: signal.Signals) -> bool:
    """Stop `proc` with `sig`; kill it if it lingers. Whether it stopped on `sig`."""
    proc.send_signal(sig)
    try:
        proc.wait(15.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5.0)
        return False
    return True


def wait_for(condition: Callable[[], bool], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"condition not met within {timeout_s} s")
        time.sleep(0.05)


def rows_in(path: Path, entity: str) -> int:
    """Rows of `entity` an aggregator has written to `path` so far (it writes as it
    receives: the SDK's flush is done when the rows are sent, the file a little later).
    """
    try:
        return summarize(path).rows[entity] if path.exists() else 0
    except Exception:  # a message half written
        return 0


def log_steps(tel: Telemetry, first: int, count: int) -> int:
    for k in range(first, first + count):
        tel.log_step(
            "r1", t_s=0.1 * k, step=k, pose=Pose2D(0.01 * k, 0.0, 0.0),
            cmd=Twist2D(0.1, 0.0), measured=Twist2D(0.1, 0.0),
            tracking=LiveErrors(Pose2D(0.01 * k, 1.0, 0.0), 0.1, 0.2, 0.3),
        )  # fmt: skip
    return first + count


def test_absent_viewer_costs_nothing_but_counted_drops(tmp_path: Path) -> None:
    url = f"rerun+http://127.0.0.1:{free_tcp_port()}/proxy"
    tel = Telemetry(
        recording_id="absent", sink=TelemetrySink(kind="tee", path=tmp_path / "a.rrd", url=url)
    )
    with tel:
        log_steps(tel, 0, 50)
        assert tel.flush(10.0)
        assert not tel.viewer_live
    assert tel.dropped == 50  # every entry missed the viewer ...
    assert summarize(tmp_path / "a.rrd").rows["/robots/r1/pose"] == 50  # ... none the file


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full on this system")
def test_a_file_sink_on_a_full_disk_is_left_out_and_its_entries_counted(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The SDK writes a file's header when it opens it: on a full disk (/dev/full answers
    every write with ENOSPC) that fails, and a robot must keep driving without it."""
    with Telemetry(
        recording_id="full", sink=TelemetrySink(kind="file", path=Path("/dev/full"))
    ) as tel:
        log_steps(tel, 0, 25)
        assert tel.flush(10.0)
    assert tel.dropped == 25
    assert "could not open the file sink /dev/full: " in caplog.text
    assert "No space left on device" in caplog.text


def test_viewer_that_goes_and_comes_back(tmp_path: Path) -> None:
    port = free_tcp_port()
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    first, second = tmp_path / "first.rrd", tmp_path / "second.rrd"
    file_sink = tmp_path / "all.rrd"
    with aggregator(port, first):
        tel = Telemetry(
            recording_id="flaky", sink=TelemetrySink(kind="tee", path=file_sink, url=url)
        )
        tel.log_world(circles=[(3.0, 0.0, 0.5)], polygons=[])
        wait_for(lambda: tel.viewer_live, 10.0)
        k = log_steps(tel, 0, 40)
        assert tel.flush(10.0)
        wait_for(lambda: rows_in(first, "/robots/r1/pose") == 40, 10.0)
    wait_for(lambda: not tel.viewer_live, 10.0)
    k = log_steps(tel, k, 30)  # nobody listening: dropped and counted
    assert tel.flush(10.0)
    assert tel.dropped == 30
    with aggregator(port, second):
        wait_for(lambda: tel.viewer_live, 10.0)
        k = log_steps(tel, k, 20)
        tel.close()
        wait_for(lambda: rows_in(second, "/robots/r1/pose") == 20, 10.0)
    tel.close()  # safe twice
    assert summarize(first).rows["/robots/r1/pose"] == 40
    back = summarize(second)
    assert back.rows["/robots/r1/pose"] == 20
    assert back.rows["/world/obstacles"] >= 1  # static entities re-sent on reconnect
    assert back.recording_ids == summarize(first).recording_ids  # the same recording
    assert summarize(file_sink).rows["/robots/r1/pose"] == 90  # the file has everything


def test_view_web_serves_the_viewer_on_loopback_and_takes_a_stream(tmp_path: Path) -> None:
    grpc, web = free_tcp_port(), free_tcp_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "phalanx", "view", "--web", "--port", str(grpc),
         "--web-port", str(web), "--memory-limit", "200MB"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        url = f"rerun+http://127.0.0.1:{grpc}/proxy"
        wait_for(lambda: viewer_reachable(url), 30.0)
        wait_for(lambda: viewer_reachable(f"rerun+http://127.0.0.1:{web}/"), 30.0)
        with urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=10) as page:
            assert page.status == 200
            assert b"<html" in page.read(4096).lower()
        tel = Telemetry(recording_id="web", sink=TelemetrySink(kind="grpc", url=url))
        with tel:
            wait_for(lambda: tel.viewer_live, 10.0)
            log_steps(tel, 0, 20)
            assert tel.flush(10.0)
        assert tel.dropped == 0
        listening = subprocess.run(
            ["ss", "-ltnH", f"( sport = :{grpc} or sport = :{web} )"],
            capture_output=True, text=True, check=False,
        ).stdout  # fmt: skip
        if listening:  # `ss` is there: nothing listens beyond loopback
            assert all(" 127.0.0.1:" in line for line in listening.splitlines()), listening
    finally:
        stopped = stop(proc, signal.SIGTERM)
    assert stopped, "phalanx view did not stop on SIGTERM"
    # ... and took the viewer with it: nothing is left serving either port
    wait_for(lambda: not viewer_reachable(f"rerun+http://127.0.0.1:{grpc}/proxy"), 10.0)
    assert not viewer_reachable(f"rerun+http://127.0.0.1:{web}/")
