"""Wire codec: round trips in both forms, and total decoding of hostile payloads."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from phalanx.core.quantities import MAX_EXTENT_M, MAX_SPEED_MPS, MAX_YAW_RATE_RADPS
from phalanx.core.states import State
from phalanx.wire.codec import DecodeStats, decode, encode
from phalanx.wire.messages import MAX_STAMP_S, RobotState, SenseFrame, VelocityCommand


def _within(bound: float) -> st.SearchStrategy[float]:
    return st.floats(min_value=-bound, max_value=bound, allow_nan=False)


names = st.from_regex(r"\A[A-Za-z0-9_-]{1,12}\Z")
# Every value the wire allows, to its bounds: all of them survive both forms. (A robot
# never tracks itself: the wire refuses a state whose leader_id is its own id.)
_FIELDS = {
    "seq": st.integers(0, 2**32 - 1),
    "stamp_s": st.floats(min_value=0.0, max_value=MAX_STAMP_S),
    "x_m": _within(MAX_EXTENT_M),
    "y_m": _within(MAX_EXTENT_M),
    "theta_rad": _within(2 * math.pi),
    "v_mps": _within(MAX_SPEED_MPS),
    "omega_radps": _within(MAX_YAW_RATE_RADPS),
    "fsm_state": st.sampled_from([str(s) for s in State]),
    "obstacle": st.booleans(),
    "direction": st.sampled_from([-1, 1]),
    "epoch": st.integers(0, 2**32 - 1),
}
states = (
    st.tuples(names, names | st.just(""))
    .filter(lambda ids: ids[0] != ids[1])
    .flatmap(
        lambda ids: st.builds(
            RobotState, robot_id=st.just(ids[0]), leader_id=st.just(ids[1]), **_FIELDS
        )
    )
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


def _state(robot_id: str, stamp_s: float, **fields: object) -> RobotState:
    return RobotState(
        robot_id=robot_id, seq=3, stamp_s=stamp_s, x_m=1.0, y_m=-0.5, theta_rad=0.2,
        v_mps=0.15, omega_radps=0.05, fsm_state="FORMATION_TRACK", **fields,  # type: ignore[arg-type]
    )  # fmt: skip


# A lockstep frame: two other robots' states of earlier ticks, one with a covariance.
RELAYED = FRAME.model_copy(
    update={"peers": (_state("r2", 0.6, cov=(0.01, 0.0, 0.0, 0.01, 0.0, 0.001)), _state("r3", 0.4))}
)


@pytest.mark.parametrize("frame", [FRAME, RELAYED], ids=["alone", "with-states"])
def test_every_truncation_is_dropped_and_counted(frame: SenseFrame) -> None:
    payload = encode(frame, "packed")
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


@pytest.mark.parametrize("fmt", ["packed", "json"])
def test_a_frame_carries_the_other_robots_states_whole(fmt: str) -> None:
    got = decode(SenseFrame, encode(RELAYED, fmt))  # type: ignore[arg-type]
    assert got == RELAYED
    assert got is not None
    assert got.peers[0].cov == RELAYED.peers[0].cov


@pytest.mark.parametrize(
    "peers",
    [
        (_state("r2", 0.7),),  # the frame's own tick: not heard yet
        (_state("r2", 0.9),),
        (_state("r1", 0.6),),  # the receiver's own state
        (_state("r2", 0.6), _state("r2", 0.5)),  # one robot twice
    ],
)
def test_a_frame_relaying_impossible_states_is_refused(peers: tuple[RobotState, ...]) -> None:
    bad = FRAME.model_construct(**{**dict(FRAME), "peers": peers})
    for fmt in ("packed", "json"):
        stats = DecodeStats()
        assert decode(SenseFrame, encode(bad, fmt), stats) is None  # type: ignore[arg-type]
        assert stats.malformed["SenseFrame"] == 1
        assert "other robots' states (one each) of earlier ticks" in stats.last_error


def test_a_relayed_state_outside_the_fleet_bounds_sinks_the_frame() -> None:
    from phalanx.wire.bounds import FleetBounds

    bounds = FleetBounds(
        robot_ids=frozenset({"r1", "r2"}), v_max_mps=1.0, omega_max_radps=2.0, t_max_s=100.0,
        dt_s=0.1, ticks=1000,
    )  # fmt: skip
    stats = DecodeStats()
    assert decode(SenseFrame, encode(RELAYED, "packed"), stats, bounds) is None  # r3: no robot
    assert "not a robot of this fleet" in stats.last_error
    fine = RELAYED.model_copy(update={"peers": RELAYED.peers[:1]})
    assert decode(SenseFrame, encode(fine, "packed"), stats, bounds) == fine
