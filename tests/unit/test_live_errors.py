"""Live telemetry errors: the paper's errors against the leader's state dead-reckoned to
the follower's time, so a follower exactly on its slot reads zero whatever the age."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from phalanx.core.config import FormationConfig, SlotConfig
from phalanx.core.formation import resolve_formation
from phalanx.core.geometry import Twist2D
from phalanx.core.rigid_body import live_errors, predict_leader, rigid_body_target
from phalanx.wire.messages import RobotState

WEDGE = resolve_formation(
    FormationConfig(
        slots=(
            SlotConfig(robot="r1", x_m=0.0, y_m=0.0),
            SlotConfig(robot="r2", follows="r1", l_m=1.0, phi_deg=135.0),
        )
    )
)


def leader_state(stamp_s: float, twist: Twist2D) -> RobotState:
    return RobotState(
        robot_id="r1", seq=1, stamp_s=stamp_s, x_m=2.0, y_m=-1.0, theta_rad=0.3,
        v_mps=twist.v_mps, omega_radps=twist.omega_radps, fsm_state="NAVIGATE",
    )  # fmt: skip


@given(
    st.floats(-0.3, 0.3),
    st.floats(-0.5, 0.5),
    st.floats(0.0, 0.5),
)
def test_on_the_slot_of_the_dead_reckoned_leader_reads_zero(
    v_mps: float, omega_radps: float, age_s: float
) -> None:
    twist = Twist2D(v_mps, omega_radps)
    state = leader_state(10.0, twist)
    now = predict_leader(state.pose, twist, age_s)
    target, _ = rigid_body_target(now, twist, WEDGE.slot_of("r2", "r1"))
    errors = live_errors(WEDGE, "r2", target, state, t_s=10.0 + age_s)
    assert errors.linear_pct == pytest.approx(0.0, abs=1e-6)
    assert errors.angular_pct == pytest.approx(0.0, abs=1e-6)
    assert errors.orientation_deg == pytest.approx(0.0, abs=1e-6)


def test_a_follower_left_behind_by_the_age_reads_the_lag() -> None:
    twist = Twist2D(0.15, 0.0)
    state = leader_state(10.0, twist)
    on_old_slot, _ = rigid_body_target(state.pose, twist, WEDGE.slot_of("r2", "r1"))
    errors = live_errors(WEDGE, "r2", on_old_slot, state, t_s=10.1)
    # 0.1 s at 0.15 m/s along the heading: 15 mm, seen from 1 m at 135 deg
    expected_m = math.hypot(-0.7071 - 0.015, 0.7071) - 1.0
    assert errors.linear_pct == pytest.approx(100.0 * abs(expected_m), rel=1e-2)
