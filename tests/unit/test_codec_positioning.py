"""The wire's positioning parts: a state's pose covariance, pose fixes, relative
measurements, and the measurements a sense frame carries; hostile values dropped."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from phalanx.core.fixes import PoseFix, RelativeFix
from phalanx.core.peers import PeerState
from phalanx.runtime.positioning import (
    flatten_fixes,
    flatten_relative,
    frame_fixes,
    frame_relative,
)
from phalanx.wire.codec import DecodeStats, decode, encode
from phalanx.wire.messages import RobotState, SenseFrame
from phalanx.wire.positions import PoseFixMessage, RelativeFixMessage

STATE = {
    "robot_id": "r2", "seq": 3, "stamp_s": 1.5, "x_m": 1.0, "y_m": 2.0, "theta_rad": 0.1,
    "v_mps": 0.15, "omega_radps": 0.0, "fsm_state": "FORMATION_TRACK",
}  # fmt: skip
COV = (4e-6, 1e-7, -2e-7, 5e-6, 3e-7, 1e-5)


@pytest.mark.parametrize("fmt", ["packed", "json"])
def test_a_state_carries_its_covariance_and_costs_two_bytes_without(fmt: str) -> None:
    with_cov = RobotState(**STATE, cov=COV)
    assert decode(RobotState, encode(with_cov, fmt)) == with_cov  # type: ignore[arg-type]
    assert with_cov.peer().cov == COV
    assert RobotState.of(PeerState(**STATE, cov=COV)) == with_cov
    bare = RobotState(**STATE)
    if fmt == "packed":
        assert len(encode(with_cov, "packed")) == len(encode(bare, "packed")) + 6 * 8


@pytest.mark.parametrize(
    "cov",
    [
        (1.0, 0.0, 0.0),  # not 6 values
        (-1e-6, 0.0, 0.0, 1e-6, 0.0, 1e-6),  # a negative variance
        (1e-6, 1e-3, 0.0, 1e-6, 0.0, 1e-6),  # a covariance its variances cannot have
        (1e7, 0.0, 0.0, 1.0, 0.0, 1.0),  # 3 km of uncertainty: a broken sender
        (1.0, 0.0, 0.0, 1.0, 0.0, 20.0),  # a heading variance beyond pi^2
    ],
)
def test_an_impossible_covariance_is_dropped_and_counted(cov: tuple[float, ...]) -> None:
    poisoned = RobotState.model_construct(**{**RobotState(**STATE).model_dump(), "cov": cov})
    stats = DecodeStats()
    assert decode(RobotState, encode(poisoned, "packed"), stats) is None
    assert stats.malformed["RobotState"] == 1


finite = st.floats(min_value=-100.0, max_value=100.0, allow_nan=False)
positive = st.floats(min_value=1e-6, max_value=1.0)


@given(
    finite, finite, st.floats(-3.0, 3.0), positive, positive, st.sampled_from(["packed", "json"])
)
def test_fixes_round_trip(x: float, y: float, th: float, s_m: float, s_r: float, fmt: str) -> None:
    fix = PoseFixMessage(robot_id="r1", stamp_s=1.7e9, x_m=x, y_m=y, theta_rad=th, std_m=s_m,
                         std_rad=s_r)  # fmt: skip
    assert decode(PoseFixMessage, encode(fix, fmt)) == fix  # type: ignore[arg-type]
    rel = RelativeFixMessage(robot_id="r2", target_id="r1", stamp_s=1.7e9, range_m=abs(x),
                             bearing_rad=th, std_range_m=s_m, std_bearing_rad=s_r)  # fmt: skip
    assert decode(RelativeFixMessage, encode(rel, fmt)) == rel  # type: ignore[arg-type]


def test_fixes_out_of_physics_are_dropped() -> None:
    good = PoseFixMessage(robot_id="r1", stamp_s=1.0, x_m=0.0, y_m=0.0, theta_rad=0.0,
                          std_m=0.002, std_rad=0.002)  # fmt: skip
    stats = DecodeStats()
    for field, value in (("x_m", 1e9), ("std_m", 0.0), ("std_rad", -1.0), ("theta_rad", 99.0)):
        bad = good.model_construct(**{**good.model_dump(), field: value})
        assert decode(PoseFixMessage, encode(bad, "packed"), stats) is None
    assert stats.malformed["PoseFixMessage"] == 4


def test_a_sense_frame_carries_what_reached_the_robot() -> None:
    ids = ("r1", "r2", "r3")
    fixes = (
        PoseFix(1.23, 1.0, 2.0, 0.5, 0.002, 0.001),
        PoseFix(1.24, 1.01, 2.0, 0.5, 0.002, 0.001),
    )
    relative = (
        RelativeFix(1.2, "r1", 1.0, -0.7, 0.02, 0.017, 0.1, 0.017),
        RelativeFix(1.2, "r3", 1.4, -1.5, 0.03, 0.017),  # no heading
    )
    frame = SenseFrame(
        robot_id="r2", tick=12, t_s=1.2, dt_s=0.1, x_m=0.0, y_m=0.0, theta_rad=0.0,
        v_mps=0.0, omega_radps=0.0, fixes=flatten_fixes(fixes),
        relative=flatten_relative(relative, ids),
    )  # fmt: skip
    back = decode(SenseFrame, encode(frame, "packed"))
    assert back is not None
    assert frame_fixes(back) == fixes
    assert frame_relative(back, ids) == relative
    # a target index past the scenario's robots is left out, a torn group refused
    odd = frame.model_copy(
        update={"relative": (*frame.relative[:8], 1.2, 7.0, *frame.relative[10:16])}
    )
    assert [r.target_id for r in frame_relative(odd, ids)] == ["r1"]
    torn = frame.model_construct(**{**frame.model_dump(), "fixes": frame.fixes[:-1]})
    stats = DecodeStats()
    assert decode(SenseFrame, encode(torn, "packed"), stats) is None
    assert math.isclose(stats.malformed["SenseFrame"], 1)
