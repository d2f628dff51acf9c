"""Robots that move on their own are recorded, not simulated: from the best pose source
heard of each (a simulator's true pose, motion capture, else the robot's own estimate),
interpolated at the run's ticks; a run ends whole when every robot finished its last
step, whether or not its process outlived the world's last tick."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.runlog import ESTIMATE_POSE, MOCAP_POSE, truth_source
from phalanx.runtime.clock import EpochClock
from phalanx.runtime.observed import ObservedRobots, Track, path_headings
from phalanx.runtime.run_record import completeness, done_when_it_left
from phalanx.simulator.world import World
from phalanx.wire.bounds import FleetBounds
from phalanx.wire.messages import AgentReport
from phalanx.wire.positions import PoseFixMessage, TruthMessage

SCENARIOS = CONFIG_ROOT / "scenarios"
BOUNDS = FleetBounds(frozenset({"r1", "r2"}), 2.0, 5.0, t_max_s=60.0, dt_s=0.1, ticks=600)


def _truth(
    rid: str, epoch_s: float, t_s: float, x: float, *, theta: float = 0.0, v: float = 0.2
) -> TruthMessage:
    return TruthMessage(
        robot_id=rid, stamp_s=epoch_s + t_s, x_m=x, y_m=1.0, theta_rad=theta, v_mps=v,
        omega_radps=0.0, source="AMRISim SIMSTAT",
    )  # fmt: skip


def test_a_track_interpolates_between_samples_and_holds_past_its_ends() -> None:
    track = Track()
    for t, x in ((0.05, 0.0), (0.15, 0.02), (0.25, 0.04)):
        track.add((t, x, 0.0, 0.0, 0.2, 0.0), capacity=10, now_s=0.5)
    track.add(
        (0.2, 9.9, 0.0, 0.0, 0.0, 0.0), capacity=10, now_s=0.5
    )  # older than the last: dropped
    assert track.dropped == 1
    rows = track.resampled(np.array([0.0, 0.1, 0.2, 0.5]))
    assert rows is not None
    assert rows[0] == pytest.approx([0.0, 0.01, 0.03, 0.04])
    seen = track.at(0.3)
    assert seen is not None
    assert seen[0].x_m == pytest.approx(0.04 + 0.2 * 0.05)  # carried along its twist
    assert track.at(0.0) is None  # nothing before the first sample


def test_headings_interpolate_the_short_way_round() -> None:
    track = Track()
    track.add((0.0, 0.0, 0.0, math.radians(179.0), 0.0, 0.0), capacity=10, now_s=0.5)
    track.add((1.0, 0.0, 0.0, math.radians(-179.0), 0.0, 0.0), capacity=10, now_s=0.5)
    rows = track.resampled(np.array([0.5]))
    assert rows is not None
    assert abs(math.degrees(float(rows[2][0]))) == pytest.approx(180.0)


def test_the_best_source_wins_and_is_named() -> None:
    epoch = time.time()  # (samples are kept only if stamped near now)
    observed = ObservedRobots(("r1", "r2"), fleet="f", epoch_s=epoch, bounds=BOUNDS)
    fix = PoseFixMessage(
        robot_id="r2", stamp_s=epoch + 0.1, x_m=3.0, y_m=4.0, theta_rad=0.5, std_m=0.002,
        std_rad=0.002,
    )  # fmt: skip
    observed._on_fix("", fix)
    observed._on_fix("", fix.model_copy(update={"robot_id": "r1"}))
    for k in range(5):
        observed._on_truth("", _truth("r1", epoch, 0.1 * k, 0.02 * k))
    observed._on_fix("", fix.model_copy(update={"robot_id": "r1", "stamp_s": epoch + 1.0}))
    t_s = np.arange(5) * 0.1
    source, rows = observed.record("r1", t_s)
    assert source == truth_source("AMRISim SIMSTAT")
    assert rows is not None
    assert rows[0] == pytest.approx(0.02 * np.arange(5))
    assert observed.record("r2", t_s)[0] == MOCAP_POSE
    nobody = ObservedRobots(("r1",), fleet="f", epoch_s=epoch, bounds=BOUNDS)
    assert nobody.record("r1", t_s) == (ESTIMATE_POSE, None)
    assert observed.has_truth("r1")
    assert not observed.has_truth("r2")


def test_a_placed_robot_is_where_it_was_seen_and_moves_on_as_it_went() -> None:
    world = World.for_scenario(load_scenario(SCENARIOS / "paper_wedge.toml"), load_robot("p3dx"))
    world.place("r2", Pose2D(5.0, 1.0, math.pi / 2), Twist2D(0.2, 0.0))
    world.step({}, 0.5)
    pose, twist = world.truth("r2")
    assert (pose.x_m, pose.y_m) == pytest.approx((5.0, 1.1))
    assert twist == Twist2D(0.2, 0.0)


def _report(rid: str) -> AgentReport:
    return AgentReport(
        robot_id=rid, steps=10, saturations=0, accel_limited=0, dropped_messages=0,
        late_peer_steps=0,
    )  # fmt: skip


def test_a_robot_that_reported_and_left_at_the_last_tick_finished() -> None:
    """On its own clock a robot ends its last step as the world ends its last tick: its
    process may go before the world has left that tick, and that is no loss."""
    ids = ("r1", "r2")
    reports = {r: _report(r) for r in ids}
    whole = completeness(
        steps=10, ticks_run=10, absent=(), lost=[("r1", 9)], reports=reports, ids=ids
    )
    assert whole["complete"] is True
    early = completeness(
        steps=10, ticks_run=10, absent=(), lost=[("r1", 5)], reports=reports, ids=ids
    )
    assert early["incomplete_reason"] == "robot r1 went away at tick 5"
    silent = completeness(steps=10, ticks_run=10, absent=(), lost=[("r2", 9)],
                          reports={"r1": reports["r1"]}, ids=ids)  # fmt: skip
    assert "no report from r2" in str(silent["incomplete_reason"])
    assert silent["lost"] == [{"robot": "r2", "tick": 9}]


def test_a_robot_is_done_when_it_left_after_reporting_at_the_last_tick() -> None:
    reports = {"r1": _report("r1")}
    assert done_when_it_left("r1", 9, reports, steps=10)
    assert not done_when_it_left("r1", 8, reports, steps=10)  # before its last step
    assert not done_when_it_left("r2", 9, reports, steps=10)  # no report in


def test_a_clock_woken_at_its_epoch_takes_step_zero() -> None:
    """A process that waited for the epoch wakes a hair past it: that is step 0 (every
    robot ran one step short of the run before)."""
    clock = EpochClock(epoch_s=time.time() + 0.05, dt_s=0.1, steps=3)
    ticks = []
    while (tick := clock.next_tick(_Never())) is not None:
        ticks.append(tick.k)
    assert ticks == [0, 1, 2]


class _Never:
    def is_set(self) -> bool:
        return False

    def wait(self, timeout: float | None = None) -> bool:
        time.sleep(timeout or 0.0)
        return False


def test_headings_read_off_the_path_where_a_simulator_gives_whole_degrees() -> None:
    """AMRISim reports whole degrees but millimetre positions: a reverse heading 0.3 deg
    (reported 0) is read off its path to within 0.03 deg; a turn on the spot is left as
    it was reported."""
    n, v, heading = 300, -0.15, math.radians(0.3)
    travel = v * 0.1 * np.arange(n)
    x = np.trunc((10.0 + travel * math.cos(heading)) * 1000.0) / 1000.0
    y = np.trunc((5.0 + travel * math.sin(heading)) * 1000.0) / 1000.0
    read = path_headings(x, y, np.zeros(n), np.full(n, v))
    assert np.degrees(read[20:-20]) == pytest.approx(0.3, abs=0.03)  # (0.25 m each side)
    spin = np.linspace(0.0, 1.0, n)
    assert np.array_equal(path_headings(np.zeros(n), np.zeros(n), spin, np.zeros(n)), spin)
