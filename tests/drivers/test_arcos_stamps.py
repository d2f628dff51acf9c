"""The `arcos` driver stamps a robot's packets when the robot sent them: a reader the
host held up reads a cycle's worth of packets at once, and each SIP (its odometry) and
each SIMSTAT (a simulator's true pose) keeps the time of its own cycle, not the moment
the reader got round to it. Robots recorded side by side on a loaded machine stay in
step: at 0.15 m/s, 50 ms of one robot's reader is 7.5 mm between them."""

from __future__ import annotations

import itertools
import time
from dataclasses import replace

import pytest

from phalanx.drivers.arcos_tracker import CYCLE_SLACK, ArcosStats, SipTracker
from phalanx.protocols.arcos import (
    FrameParser,
    RobotConfig,
    SimStat,
    Sip,
    encode_simstat,
    encode_sip,
    factors_for,
)

SIP = Sip(moving=True, x=0, y=0, th=0, left_vel=150, right_vel=150, battery_dv=130,
          stall_bumpers=0)  # fmt: skip
SIMSTAT = SimStat(flags=0, sim_interval_ms=100, real_interval_ms=100, last_interval_ms=100,
                  x_mm=0, y_mm=0, th_deg=0)  # fmt: skip
HELD_S = 0.35  # the reader held up: three cycles and a half


def _tracker(sip_cycle_ms: int) -> tuple[SipTracker, FrameParser]:
    tracker = SipTracker(ArcosStats())
    tracker.factors = factors_for("p3dx-sh")
    tracker.config = RobotConfig(sip_cycle_ms=sip_cycle_ms)
    tracker.new_session()
    return tracker, FrameParser()


def _take(tracker: SipTracker, parser: FrameParser, data: bytes) -> list[float]:
    """The odometry stamp after each SIP of `data`, read in one go."""
    stamps = []
    for body in parser.feed(data):
        if tracker.take(body, byte_time_s=0.0) is not None:
            assert tracker.odometry is not None
            stamps.append(tracker.odometry.stamp_s)
    return stamps


def test_sips_read_in_a_burst_keep_their_cycles() -> None:
    tracker, parser = _tracker(sip_cycle_ms=100)
    (first,) = _take(tracker, parser, encode_sip(SIP))
    time.sleep(HELD_S)
    burst = b"".join(encode_sip(replace(SIP, x=k)) for k in range(1, 4))
    before_s = time.monotonic()
    stamps = _take(tracker, parser, burst)
    cycle_s = 0.1 * (1.0 + CYCLE_SLACK)
    assert stamps == pytest.approx([first + k * cycle_s for k in (1, 2, 3)], abs=1e-9)
    assert stamps[-1] < before_s  # where the arrival would have said after HELD_S


def test_a_simulators_true_pose_keeps_its_updates_real_time() -> None:
    tracker, parser = _tracker(sip_cycle_ms=100)
    truths = []
    for last_ms in (100, 130, 95):
        for body in parser.feed(encode_simstat(replace(SIMSTAT, last_interval_ms=last_ms))):
            tracker.take(body, byte_time_s=0.0)
        assert tracker.truth is not None
        truths.append(tracker.truth.odometry.stamp_s)
        time.sleep(HELD_S)
    slack = 1.0 + CYCLE_SLACK
    gaps = [b - a for a, b in itertools.pairwise(truths)]
    assert gaps == pytest.approx([0.130 * slack, 0.095 * slack], abs=1e-9)  # 130 ms, then 95


def test_without_a_cycle_the_arrival_stands() -> None:
    tracker, parser = _tracker(sip_cycle_ms=0)  # a CONFIG packet cut short of SipCycle
    (first,) = _take(tracker, parser, encode_sip(SIP))
    time.sleep(HELD_S)
    (second,) = _take(tracker, parser, encode_sip(replace(SIP, x=1)))
    assert second - first >= HELD_S
