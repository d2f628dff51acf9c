"""One suite every driver backend passes (python-can style): the Driver protocol's
promises, and the safety wrapper's, against the real backend and its robot side."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import pytest
from fleetlab import wait_for

from phalanx.core.errors import DriverError
from phalanx.core.geometry import Twist2D
from phalanx.drivers.base import Driver
from phalanx.drivers.safety import SafeDriver

Rig = Any  # the `rig` fixture of conftest.py: .driver, .robot_side, .limits

pytestmark = pytest.mark.drivers


def _speed(driver: Driver) -> Twist2D:
    return driver.read_odometry().twist


def _drive(safe: SafeDriver, twist: Twist2D, check: Callable[[], bool], timeout_s: float) -> bool:
    """Command `twist` at 20 Hz, as an agent does, until `check` holds."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        safe.set_velocity(twist)
        if check():
            return True
        time.sleep(0.05)
    return check()


def test_connect_reports_a_finite_pose_and_enabled_motors(rig: Rig) -> None:
    rig.driver.connect()
    odo = rig.driver.read_odometry()
    assert all(math.isfinite(v) for v in (odo.pose.x_m, odo.pose.y_m, odo.pose.theta_rad))
    status = rig.driver.read_status()
    assert status.motors_enabled
    assert len(status.sonar_ranges_m) in (0, 16)
    assert not status.faults


def test_forward_command_moves_forward_and_stop_stops(rig: Rig) -> None:
    rig.driver.connect()
    rig.driver.set_velocity(Twist2D(0.2, 0.0))
    assert wait_for(lambda: abs(_speed(rig.driver).v_mps - 0.2) < 0.02, 3.0, poll_s=0.02)
    assert wait_for(lambda: rig.driver.read_odometry().pose.x_m > 0.02, 2.0, poll_s=0.02)
    rig.driver.stop()
    assert wait_for(lambda: abs(_speed(rig.driver).v_mps) < 0.005, 3.0, poll_s=0.02)


def test_rotation_turns_counter_clockwise(rig: Rig) -> None:
    rig.driver.connect()
    rig.driver.set_velocity(Twist2D(0.0, 0.5))
    assert wait_for(lambda: rig.driver.read_odometry().pose.theta_rad > 0.2, 4.0, poll_s=0.02)
    assert abs(rig.driver.read_odometry().pose.x_m) < 0.02


def test_close_twice_is_safe_and_leaves_it_stopped(rig: Rig) -> None:
    rig.driver.connect()
    rig.driver.set_velocity(Twist2D(0.2, 0.0))
    rig.driver.close()
    rig.driver.close()
    with pytest.raises(DriverError):
        rig.driver.set_velocity(Twist2D(0.1, 0.0))
    if rig.zero_commanded is not None:  # the robot itself was told to stop
        assert wait_for(rig.zero_commanded, 2.0, poll_s=0.02)


def test_watchdog_stops_a_robot_whose_commands_stop(rig: Rig) -> None:
    with SafeDriver(rig.driver, rig.limits) as safe:
        assert _drive(safe, Twist2D(0.2, 0.0), lambda: _speed(safe).v_mps > 0.1, 3.0)
        silent_from = time.monotonic()
        assert wait_for(lambda: safe.stats.watchdog_stops == 1, 2.0, poll_s=0.02)
        assert time.monotonic() - silent_from < rig.limits.watchdog_s + 0.3
        assert wait_for(lambda: abs(_speed(safe).v_mps) < 0.005, 3.0, poll_s=0.02)


def test_commands_are_clamped_with_their_curvature(rig: Rig) -> None:
    with SafeDriver(rig.driver, rig.limits) as safe:
        sent = safe.set_velocity(Twist2D(1.0, 0.5))
        assert sent.v_mps == pytest.approx(rig.limits.v_max_mps)
        assert sent.omega_radps / sent.v_mps == pytest.approx(0.5)
        assert safe.stats.clamped == 1
        assert _drive(safe, Twist2D(1.0, 0.5), lambda: _speed(safe).v_mps > 0.25, 3.0)
        assert _speed(safe).v_mps <= rig.limits.v_max_mps + 0.01


def test_non_finite_command_stops_the_robot(rig: Rig) -> None:
    with SafeDriver(rig.driver, rig.limits) as safe:
        assert _drive(safe, Twist2D(0.2, 0.0), lambda: _speed(safe).v_mps > 0.1, 3.0)
        assert safe.set_velocity(Twist2D(math.nan, 0.0)) == Twist2D(0.0, 0.0)
        assert safe.stats.rejected == 1
        assert _drive(safe, Twist2D(0.0, 0.0), lambda: abs(_speed(safe).v_mps) < 0.005, 3.0)


def test_estop_latches_until_reset(rig: Rig) -> None:
    with SafeDriver(rig.driver, rig.limits) as safe:
        safe.set_velocity(Twist2D(0.2, 0.0))
        safe.estop()
        assert safe.set_velocity(Twist2D(0.2, 0.0)) == Twist2D(0.0, 0.0)
        assert safe.read_status().estopped
        assert wait_for(lambda: abs(_speed(safe).v_mps) < 0.005, 3.0, poll_s=0.02)
        safe.reset_estop()
        assert _drive(safe, Twist2D(0.1, 0.0), lambda: _speed(safe).v_mps > 0.05, 3.0)
