"""No command drives a robot into an echo it stands against: the emergency stop watches
a robot that moves, so the step that starts it moving is checked on its own.
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from phalanx.agents.navigation import clearance_along
from phalanx.agents.perception import SonarGeometry
from phalanx.agents.sensing import CONTACT_MARGIN_M, ContactGuard, Sensing
from phalanx.core.config_files import load_robot
from phalanx.core.geometry import Twist2D

RADIUS_M, DT_S, V_MAX_MPS = 0.25, 0.1, 0.3
GUARD = ContactGuard(RADIUS_M, DT_S, V_MAX_MPS)


def _sensing(x_m: float, y_m: float) -> Sensing:
    """One echo at (x, y) in the body frame."""
    raw = (np.array([x_m]), np.array([y_m]))
    return Sensing(
        points=raw, raw=raw, ahead_m=x_m, blocked={1: True, -1: False},
        path_clear=False, imminent=False, bumper=False,
    )  # fmt: skip


def test_a_robot_against_an_obstacle_does_not_creep_into_it() -> None:
    # As a follower in reverse whose slot lies ahead, past the obstacle: it asks for
    # 3 cm/s forwards while 5 mm from the obstacle.
    against = _sensing(RADIUS_M + 0.005, 0.0)
    cut = GUARD.apply(Twist2D(0.03, 0.2), against)
    assert cut == Twist2D(0.0, 0.2)  # turning is left alone
    off = ContactGuard(RADIUS_M, DT_S, V_MAX_MPS, on=False)  # scripted obstacles (the paper)
    assert off.apply(Twist2D(0.03, 0.2), against) == Twist2D(0.03, 0.2)
    away = Twist2D(-0.03, 0.0)
    assert GUARD.apply(away, against) == away
    alongside = _sensing(0.05, RADIUS_M + 0.01)  # a wall passed 1 cm off
    assert GUARD.apply(Twist2D(0.03, 0.0), alongside).v_mps
    roomy = _sensing(RADIUS_M + 0.2, 0.0)
    onward = Twist2D(0.03, 0.0)
    assert GUARD.apply(onward, roomy) == onward


@given(
    v_mps=st.floats(-1.5, 1.5),  # what a controller asks, before the limiter
    omega_radps=st.floats(-0.7, 0.7),
    range_m=st.floats(0.0, 1.0),
    bearing_rad=st.floats(-math.pi, math.pi),
)
def test_a_step_never_ends_within_the_margin_of_an_echo_the_way_it_drives(
    v_mps: float, omega_radps: float, range_m: float, bearing_rad: float
) -> None:
    echo = (
        (RADIUS_M + range_m) * math.cos(bearing_rad),
        (RADIUS_M + range_m) * math.sin(bearing_rad),
    )
    sensing = _sensing(*echo)
    wanted = Twist2D(v_mps, omega_radps)
    out = GUARD.apply(wanted, sensing)
    assert out.omega_radps == omega_radps
    assert out.v_mps in (0.0, v_mps)
    # the echo on the side it drives to (signs compared: a subnormal speed times the
    # echo's x would round to 0)
    ahead = out.v_mps != 0.0 and echo[0] * math.copysign(1.0, out.v_mps) > 0.0
    if out.v_mps != 0.0 and ahead:
        way = 0.0 if out.v_mps > 0.0 else math.pi
        gap_m = clearance_along(sensing.raw, way, half_width_m=RADIUS_M)
        assert gap_m >= min(abs(out.v_mps), V_MAX_MPS) * DT_S + CONTACT_MARGIN_M
    if out.v_mps == 0.0 and v_mps != 0.0:  # cut only for an echo it drives towards
        assert echo[0] * math.copysign(1.0, v_mps) > 0.0


P3DX = load_robot("p3dx")
RING = SonarGeometry.from_params(P3DX)


def _ring_sensing(unit: int, range_m: float) -> Sensing:
    """The P3DX ring with one transducer reading `range_m` (everything else far)."""
    ranges = np.full(len(P3DX.sonar.units), P3DX.sonar.max_range_m)
    ranges[unit] = range_m
    raw = RING.read(ranges).raw
    return Sensing(
        points=raw, raw=raw, ahead_m=0.0, blocked={1: False, -1: False},
        path_clear=False, imminent=False, bumper=False,
    )  # fmt: skip


def test_what_the_sonar_s_minimum_range_hides_is_not_driven_into() -> None:
    """A sonar reads its minimum range for anything nearer: the rear ring's transducers
    sit 4 mm inside the body's disc, so an echo read at 0.1 m may be touching it.
    """
    guard = ContactGuard(P3DX.radius_m, DT_S, V_MAX_MPS)
    low = P3DX.sonar.min_range_m
    front, rear = 3, 11  # +10 deg and -170 deg (p3dx.toml)
    assert guard.apply(Twist2D(-0.1, 0.0), _ring_sensing(rear, low)) == Twist2D(0.0, 0.0)
    assert guard.apply(Twist2D(0.05, 0.0), _ring_sensing(front, low)) == Twist2D(0.0, 0.0)
    # Driving away, and anything read beyond the minimum range, are as before.
    assert guard.apply(Twist2D(0.1, 0.0), _ring_sensing(rear, low)).v_mps == 0.1
    assert guard.apply(Twist2D(-0.1, 0.0), _ring_sensing(rear, low + 0.05)).v_mps == -0.1


@given(unit=st.integers(0, 15), range_m=st.floats(0.0, 0.1))
def test_a_minimum_range_echo_lies_just_outside_the_body_and_no_further_than_read(
    unit: int, range_m: float
) -> None:
    x, y = _ring_sensing(unit, range_m).raw
    centre_m = np.hypot(x, y)
    sensor = P3DX.sonar.units[unit]
    from_sensor_m = np.hypot(x - sensor.x_m, y - sensor.y_m)
    assert np.all(from_sensor_m <= range_m + 1e-9)  # never further off than it reads
    outside = from_sensor_m < range_m - 1e-9  # moved in: to just outside the disc
    assert np.all(np.abs(centre_m[outside] - P3DX.radius_m) < 2e-3)
