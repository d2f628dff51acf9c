"""Wire codec: round trips in both forms, and total decoding of hostile payloads."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from phalanx.wire.codec import DecodeStats, decode, encode
from phalanx.wire.messages import RobotState, SenseFrame, VelocityCommand

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False)
names = st.text(min_size=1, max_size=12)
states = st.builds(
    RobotState,
    robot_id=names,
    seq=st.integers(0, 2**32 - 1),
    stamp_s=finite,
    x_m=finite,
    y_m=finite,
    theta_rad=finite,
    v_mps=finite,
    omega_radps=finite,
    fsm_state=names,
    obstacle=st.booleans(),
    direction=st.sampled_from([-1, 1]),
    leader_id=st.text(max_size=12),
    epoch=st.integers(0, 2**32 - 1),
)
FRAME = SenseFrame(
    robot_id="r1",
    tick=7,
    t_s=0.7,
    dt_s=0.1,
    x_m=1.0,
    y_m=2.0,
    theta_rad=0.3,
    v_mps=0.1,
    omega_radps=0.0,
    sonar_ranges_m=(0.5,) * 16,
    bumpers=(False,) * 10,
)


@given(states, st.sampled_from(["packed", "json"]))
def test_robot_state_round_trips(state: RobotState, fmt: str) -> None:
    assert decode(RobotState, encode(state, fmt)) == state  # type: ignore[arg-type]


def test_packed_form_is_smaller_than_json() -> None:
    for message in (
        FRAME,
        VelocityCommand(robot_id="r1", tick=1, stamp_s=0.1, v_mps=0.1, omega_radps=0.0),
    ):
        assert len(encode(message, "packed")) < len(encode(message, "json"))


def test_every_truncation_is_dropped_and_counted() -> None:
    payload = encode(FRAME, "packed")
    stats = DecodeStats()
    for cut in range(len(payload)):
        assert decode(SenseFrame, payload[:cut], stats) is None
    assert stats.malformed["SenseFrame"] == len(payload)
    assert decode(SenseFrame, payload + b"\0", stats) is None  # trailing garbage too


@given(st.binary(max_size=300))
def test_random_bytes_never_raise(payload: bytes) -> None:
    stats = DecodeStats()
    result = decode(RobotState, payload, stats)
    assert result is not None or stats.dropped == 1


def test_unknown_version_is_counted_apart() -> None:
    payload = bytearray(encode(FRAME, "packed"))
    payload[1] = 9
    stats = DecodeStats()
    assert decode(SenseFrame, bytes(payload), stats) is None
    assert stats.unknown_version["SenseFrame"] == 1
    raw = FRAME.model_dump_json().replace('"version":1', '"version":2').encode()
    assert decode(SenseFrame, raw, stats) is None
    assert stats.unknown_version["SenseFrame"] == 2


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_numbers_are_rejected_in_both_forms(bad: float) -> None:
    good = VelocityCommand(robot_id="r1", tick=1, stamp_s=0.1, v_mps=0.1, omega_radps=0.0)
    poisoned = good.model_construct(**{**good.model_dump(), "v_mps": bad})
    stats = DecodeStats()
    assert decode(VelocityCommand, encode(poisoned, "packed"), stats) is None
    assert (
        decode(
            VelocityCommand,
            f'{{"robot_id":"r1","tick":1,"stamp_s":0.1,"v_mps":{bad},"omega_radps":0.0}}'.replace(
                "nan", "NaN"
            )
            .replace("inf", "Infinity")
            .encode(),
            stats,
        )
        is None
    )
    assert stats.malformed["VelocityCommand"] == 2


def test_a_message_of_another_kind_is_dropped() -> None:
    stats = DecodeStats()
    assert decode(RobotState, encode(FRAME, "packed"), stats) is None
    assert stats.malformed["RobotState"] == 1
