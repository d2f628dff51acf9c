"""A robot's logged steps as they reach the recording: the sonar rays drawn for a batch
of rows, the errors computed when the batch goes out, the map's extent, and the
telemetry thread's priority.
"""

from __future__ import annotations

import math
import os
import re
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from phalanx.core.config_files import load_robot
from phalanx.core.geometry import Pose2D, Twist2D, Vec2
from phalanx.core.rigid_body import LiveErrors
from phalanx.core.robot_params import SonarParams
from phalanx.telemetry.layout import sonar_segments
from phalanx.telemetry.sinks import TELEMETRY_NICE, TelemetrySink
from phalanx.telemetry.stream import Telemetry

SONAR = load_robot("p3dx").sonar
UNITS = len(SONAR.units)
ranges_row = st.lists(
    st.one_of(st.floats(0.0, 2 * SONAR.max_range_m), st.just(SONAR.max_range_m)),
    min_size=0,
    max_size=UNITS + 3,
)
poses = st.builds(
    Pose2D, st.floats(-50.0, 50.0), st.floats(-50.0, 50.0), st.floats(-math.pi, math.pi)
)


def ray_by_ray(sonar: SonarParams, pose: Pose2D, ranges_m: list[float]) -> list[list[float]]:
    """Each unit's segment, one at a time through the pose's own frame change."""
    rays = []
    for unit, range_m in zip(sonar.units, ranges_m, strict=False):
        if range_m >= sonar.max_range_m:
            continue
        start = pose.to_world(Vec2(unit.x_m, unit.y_m))
        heading = pose.theta_rad + math.radians(unit.heading_deg)
        rays.append([start.x_m, start.y_m, start.x_m + range_m * math.cos(heading),
                     start.y_m + range_m * math.sin(heading)])  # fmt: skip
    return rays


@given(st.lists(st.tuples(poses, ranges_row), min_size=1, max_size=6))
def test_batched_rays_are_each_units_ray(steps: list[tuple[Pose2D, list[float]]]) -> None:
    pose_rows = np.array([(p.x_m, p.y_m, p.theta_rad) for p, _ in steps])
    segments, counts = sonar_segments(SONAR, pose_rows, [r for _, r in steps])
    expected = [ray_by_ray(SONAR, pose, ranges) for pose, ranges in steps]
    assert counts == [len(rays) for rays in expected]
    flat = [ray for rays in expected for ray in rays]
    assert segments.shape == (len(flat), 2, 2)
    np.testing.assert_allclose(segments.reshape(-1, 4), np.reshape(flat, (-1, 4)), atol=1e-9)


def read_back(path: Path, entity: str, column: str) -> list[object]:
    """Every row's value of `column` in `entity` of the recording at `path`."""
    from rerun.chunk import RrdReader

    values: list[object] = []
    for chunk in RrdReader(str(path)).stream():
        if chunk.entity_path == entity:
            values += chunk.to_record_batch().column(column).to_pylist()
    return values


def test_the_recording_has_each_steps_rays_and_errors(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Rays and errors are made when the batch goes out: what lands in the file is what
    the step saw, and a step whose errors cannot be computed loses only those.
    """
    path = tmp_path / "steps.rrd"
    ranges = (1.5, *[SONAR.max_range_m] * (UNITS - 2), 0.75)

    def tracking(k: int) -> LiveErrors:
        if k == 3:
            raise ZeroDivisionError("a leader on its follower's slot")
        return LiveErrors(Pose2D(0.5 * k, 1.0, 0.0), 0.1 * k, 0.2, 0.3)

    visited = [Pose2D(0.5 * k, 0.1 * k, 0.2 * k) for k in range(6)]
    with Telemetry(recording_id="rows", sink=TelemetrySink(kind="file", path=path)) as tel:
        for k, pose in enumerate(visited):
            tel.log_step(
                "r2", t_s=0.1 * k, step=k, pose=pose, cmd=Twist2D(0.1, 0.0),
                measured=Twist2D(0.1, 0.0), tracking=lambda k=k: tracking(k), sonar=SONAR,
                sonar_ranges_m=ranges, fsm_state="FORMATION_TRACK", leader_id="r1",
            )  # fmt: skip
    strips = read_back(path, "/robots/r2/sonar", "LineStrips2D:strips")
    assert len(strips) == len(visited)
    for pose, row in zip(visited, strips, strict=True):
        expected = np.reshape(ray_by_ray(SONAR, pose, list(ranges)), (-1, 2, 2))
        np.testing.assert_allclose(np.array(row), expected, atol=1e-5)  # stored as float32
    linear = read_back(path, "/robots/r2/errors/linear_pct", "Scalars:scalars")
    assert [v for (v,) in linear] == pytest.approx([0.0, 0.1, 0.2, 0.4, 0.5])  # not step 3
    failures = [r for r in caplog.records if "could not be computed" in r.getMessage()]
    assert len(failures) == 1  # one line for the batch (6 steps, unless the host stalled)
    assert re.fullmatch(r"telemetry: the errors of 1 of \d steps could not be computed",
                        failures[0].getMessage())  # fmt: skip
    assert failures[0].exc_info is not None
    assert len(read_back(path, "/robots/r2/pose", "Points2D:positions")) == len(visited)
    labels = read_back(path, "/robots/r2/pose", "Points2D:labels")
    assert labels[0] == ["r2 FORMATION_TRACK -> r1"]


def test_the_map_is_framed_on_every_position_logged(tmp_path: Path) -> None:
    tel = Telemetry(recording_id="box", sink=TelemetrySink(kind="memory"))
    with tel:
        for x, y in [(1.0, 2.0), (-3.0, 0.5), (2.5, -4.0), (0.0, 0.0)]:
            tel.log_truth("r1", t_s=0.0, pose=Pose2D(x, y, 0.0))
        assert tel._extent.framed(0.0) == (-3.0, 2.5, -4.0, 2.0)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice is Linux's")
def test_beside_a_control_loop_the_telemetry_thread_runs_at_the_lowest_priority() -> None:
    own = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    sink = TelemetrySink(kind="memory")
    with (
        Telemetry(recording_id="live", sink=sink, background=True) as live,
        Telemetry(recording_id="after", sink=sink) as after,
    ):
        live_worker, after_worker = live._outbox._worker, after._outbox._worker
        assert live_worker is not None
        assert after_worker is not None
        assert live_worker.native_id is not None
        assert after_worker.native_id is not None
        deadline = time.monotonic() + 5.0
        while os.getpriority(os.PRIO_PROCESS, live_worker.native_id) != TELEMETRY_NICE:
            assert time.monotonic() < deadline, "the telemetry thread kept its priority"
            time.sleep(0.01)
        # a recording written after a run keeps the priority it was given: nothing else
        # waits, and on a busy host a low-priority thread might not finish it in time
        assert os.getpriority(os.PRIO_PROCESS, after_worker.native_id) == own
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == own  # only it
