"""Wire bounds: what a field may hold, what a receiver that knows its fleet refuses, and
how what is refused (or lost in a full ring, or fails its handler) is counted."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from typing import Any

import pytest

from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.wire.bounds import FleetBounds
from phalanx.wire.codec import DecodeStats, decode, encode
from phalanx.wire.delivery import Polled, deliver
from phalanx.wire.messages import LeaderAnnouncement, RobotFlags, RobotState, SenseFrame

SCENARIO = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
BOUNDS = FleetBounds.of(SCENARIO, load_robot(SCENARIO.robot))
STATE = RobotState(robot_id="r2", seq=3, stamp_s=1.2, x_m=1.0, y_m=0.5, theta_rad=0.1,
                   v_mps=0.15, omega_radps=0.0, fsm_state="FORMATION_TRACK", leader_id="r1",
                   formation_leader_id="r1")  # fmt: skip


def _json(**changes: Any) -> bytes:
    return json.dumps({**STATE.model_dump(), **changes}).encode()


@pytest.mark.parametrize(
    "changes",
    [
        {"epoch": 2**40},  # beyond the 32 bits it travels in
        {"seq": -1},
        {"stamp_s": 1e308},
        {"x_m": 1e300},
        {"v_mps": 50.0},  # no robot phalanx drives is that fast
        {"theta_rad": 100.0},
        {"fsm_state": "DANCING"},
        {"robot_id": "r1/../x"},
        {"reason": "x"},  # unknown field
    ],
)
def test_every_field_is_bounded_by_the_protocol_and_physics(changes: dict[str, Any]) -> None:
    stats = DecodeStats()
    assert decode(RobotState, _json(**changes), stats) is None
    assert stats.malformed["RobotState"] == 1


@pytest.mark.parametrize(
    "changes",
    [
        {"robot_id": "r9"},  # not in the fleet
        {"leader_id": "b1"},
        {"v_mps": 2.0},  # beyond the P3DX's rating (1.2 m/s, with a margin)
        {"stamp_s": 400.0},  # after the 200 s run's end
    ],
)
def test_a_receiver_that_knows_its_fleet_refuses_more(changes: dict[str, Any]) -> None:
    assert decode(RobotState, _json(**changes)) is not None  # fine for anyone else
    stats = DecodeStats()
    assert decode(RobotState, _json(**changes), stats, BOUNDS) is None
    assert stats.malformed["RobotState"] == 1


def test_a_sense_frame_keeps_to_its_tick_and_the_runs_period() -> None:
    base = {"robot_id": "r2", "tick": 10, "t_s": 1.0, "dt_s": 0.1, "x_m": 0.0, "y_m": 0.0,
            "theta_rad": 0.0, "v_mps": 0.0, "omega_radps": 0.0}  # fmt: skip
    assert decode(SenseFrame, json.dumps(base).encode(), None, BOUNDS) is not None
    for wrong in ({"t_s": sys.float_info.max}, {"t_s": 150.0}, {"dt_s": 0.05, "t_s": 0.5},
                  {"tick": 10**6, "t_s": 10**5}):  # fmt: skip
        assert decode(SenseFrame, json.dumps({**base, **wrong}).encode(), None, BOUNDS) is None


def test_no_payload_makes_the_decoder_raise() -> None:
    stats = DecodeStats()
    for payload in (
        b"[" * 100_000,
        b"{" + b'"a":' * 1000,
        bytes(70_000),
        b"\x01\x01" + b"\xff" * 9,
    ):
        assert decode(RobotFlags, payload, stats) is None
    assert stats.malformed["RobotFlags"] == 4


@dataclass
class _Sample:
    key_expr: str
    payload: Any


@dataclass
class _Bytes:
    raw: bytes

    def to_bytes(self) -> bytes:
        return self.raw


def test_a_message_on_another_robots_key_is_rejected_and_counted() -> None:
    stats, got = DecodeStats(), []
    deliver(
        "phalanx/f/robot/r3/state", encode(STATE), RobotState, stats, lambda k, m: got.append(m)
    )
    assert got == []
    assert stats.rejected["RobotState"] == 1
    deliver(
        "phalanx/f/robot/r2/state", encode(STATE), RobotState, stats, lambda k, m: got.append(m)
    )
    assert got == [STATE]


def test_a_failing_handler_is_counted_never_raised() -> None:
    stats = DecodeStats()

    def boom(_key: str, _message: LeaderAnnouncement) -> None:
        raise OverflowError("a bug")

    message = LeaderAnnouncement(leader_id="r2", epoch=1, stamp_s=1.0)
    deliver("phalanx/f/leader", encode(message), LeaderAnnouncement, stats, boom)
    assert stats.handler_errors["LeaderAnnouncement"] == 1
    assert stats.dropped == 1


def test_a_full_ring_counts_every_payload_it_drops() -> None:
    stats = DecodeStats()
    ring: Polled[RobotFlags] = Polled(RobotFlags, stats, capacity=8, context=BOUNDS)
    flags = encode(STATE.flags())
    for _ in range(100):
        ring.put(_Sample("phalanx/f/robot/r2/flags", _Bytes(flags)))
    got: list[RobotFlags] = []
    assert ring.drain(lambda _k, m: got.append(m)) == 8
    assert len(got) == 8
    assert stats.ring_dropped["RobotFlags"] == 92
    assert stats.dropped + sum(stats.ok.values()) == 100  # every payload accounted for
