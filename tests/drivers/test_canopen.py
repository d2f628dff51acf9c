"""The CiA 402 backend against simulated drives on python-can's virtual bus: the 402
state machine, supervision (heartbeat, EMCY, FAULT), and a clean close."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator

import can
import pytest
from fleetlab import wait_for

from phalanx.core.config_files import load_robot
from phalanx.core.errors import DriverError, DriverUnavailable
from phalanx.core.geometry import Twist2D
from phalanx.core.robot_params import RobotParams
from phalanx.drivers.canopen import CanopenDriver, CanopenSettings
from phalanx.protocols.cia402 import SW_OPERATION_ENABLED, SW_SWITCH_ON_DISABLED, Cw
from phalanx.simulator.cia402 import SimulatedDiffDrive, next_state

pytestmark = pytest.mark.drivers
ROBOT = load_robot("p3dx")


@pytest.fixture
def rig(request: pytest.FixtureRequest) -> Iterator[tuple[SimulatedDiffDrive, CanopenDriver]]:
    channel = f"can-{request.node.name}"
    with SimulatedDiffDrive(channel) as drives:
        driver = CanopenDriver(CanopenSettings(interface="virtual", channel=channel), robot=ROBOT)
        try:
            yield drives, driver
        finally:
            driver.close()


def test_state_machine_walks_to_operation_enabled_and_back() -> None:
    state = SW_SWITCH_ON_DISABLED
    for command in (Cw.SHUTDOWN, Cw.SWITCH_ON, Cw.ENABLE_OPERATION):
        state = next_state(state, command, 0)
    assert state == SW_OPERATION_ENABLED
    assert next_state(state, Cw.QUICK_STOP, Cw.ENABLE_OPERATION) == 0x07
    assert next_state(state, Cw.DISABLE_VOLTAGE, Cw.ENABLE_OPERATION) == SW_SWITCH_ON_DISABLED
    # A fault clears only on the rising edge of bit 7.
    assert next_state(0x08, Cw.FAULT_RESET, Cw.FAULT_RESET) == 0x08
    assert next_state(0x08, Cw.FAULT_RESET, 0) == SW_SWITCH_ON_DISABLED


def test_connect_enables_both_drives_in_profile_velocity(
    rig: tuple[SimulatedDiffDrive, CanopenDriver],
) -> None:
    drives, driver = rig
    driver.connect()
    assert all(d.state == SW_OPERATION_ENABLED for d in drives.drives)
    assert all(d.node.sdo[0x6060].raw == 3 for d in drives.drives)
    assert all(d.node.nmt.state == "OPERATIONAL" for d in drives.drives)


def test_wheel_targets_follow_the_geometry_and_mounting(
    rig: tuple[SimulatedDiffDrive, CanopenDriver],
) -> None:
    drives, driver = rig
    driver.connect()
    s = driver.settings
    driver.set_velocity(Twist2D(0.2, 0.5))
    half = 0.5 * ROBOT.track_width_m / 2
    left = (0.2 - half) / ROBOT.wheel_radius_m * s.counts_per_radps
    right = (0.2 + half) / ROBOT.wheel_radius_m * s.counts_per_radps
    assert wait_for(lambda: drives.left.target == round(left), 1.0)
    assert drives.right.target == round(-right)  # mirrored mounting: right_sign = -1
    assert wait_for(lambda: abs(driver.read_odometry().twist.omega_radps - 0.5) < 0.01, 2.0)
    assert driver.read_odometry().twist.v_mps == pytest.approx(0.2, abs=0.005)


def test_wheel_speed_limit_scales_both_wheels(
    rig: tuple[SimulatedDiffDrive, CanopenDriver],
) -> None:
    drives, driver = rig
    driver.connect()
    driver.set_velocity(Twist2D(5.0, 0.0))  # far above the wheel speed limit
    limit = driver.geometry.max_radps * driver.settings.counts_per_radps
    assert wait_for(lambda: drives.left.target != 0, 1.0)
    assert abs(drives.left.target) <= round(limit)
    assert abs(drives.right.target) <= round(limit)


def test_the_wheels_are_the_robot_files() -> None:
    geometry = CanopenDriver(CanopenSettings(), robot=ROBOT).geometry
    assert geometry.radius_m == ROBOT.wheel_radius_m == 0.0975
    assert geometry.track_width_m == ROBOT.track_width_m == 0.357
    assert geometry.max_radps == pytest.approx(ROBOT.wheel_v_max_mps / ROBOT.wheel_radius_m)


@pytest.mark.parametrize("radius_m", [0.0975, 0.15])
def test_the_wheel_speed_sent_follows_the_robot_files_wheel_radius(
    request: pytest.FixtureRequest, radius_m: float
) -> None:
    robot = _robot_with(wheel_radius_m=radius_m)
    channel = f"geometry-{request.node.name}"
    with SimulatedDiffDrive(channel) as drives:
        settings = CanopenSettings(interface="virtual", channel=channel)
        with CanopenDriver(settings, robot=robot) as driver:
            driver.set_velocity(Twist2D(0.2, 0.0))
            counts = round(0.2 / radius_m * settings.counts_per_radps)  # 2051 or 1333
            assert wait_for(lambda: drives.left.target == counts, 1.0), drives.left.target
            assert drives.right.target == -counts  # mounted mirrored


def test_the_wheel_speed_limit_is_the_robot_files_wheel_rim_speed(
    request: pytest.FixtureRequest,
) -> None:
    robot = _robot_with(wheel_v_max_mps=0.5)
    channel = f"limit-{request.node.name}"
    with SimulatedDiffDrive(channel) as drives:
        settings = CanopenSettings(interface="virtual", channel=channel)
        with CanopenDriver(settings, robot=robot) as driver:
            driver.set_velocity(Twist2D(1.0, 0.0))  # twice the rim speed
            counts = round(0.5 / robot.wheel_radius_m * settings.counts_per_radps)
            assert wait_for(lambda: drives.left.target == counts, 1.0), drives.left.target


def _robot_with(**fields: float) -> RobotParams:
    return RobotParams.model_validate({**ROBOT.model_dump(), **fields})


def test_lost_heartbeat_stops_both_wheels(rig: tuple[SimulatedDiffDrive, CanopenDriver]) -> None:
    drives, driver = rig
    driver.connect()
    driver.set_velocity(Twist2D(0.2, 0.0))
    assert wait_for(lambda: abs(drives.left.velocity) > 1000, 2.0)
    lost_at = time.monotonic()
    drives.right.lose_heartbeat()
    assert wait_for(lambda: bool(driver.read_status().faults), 2.0)
    assert time.monotonic() - lost_at < driver.settings.heartbeat_timeout_s + 0.2
    assert "heartbeat" in driver.read_status().faults[0]
    assert wait_for(lambda: drives.left.target == 0, 0.5)  # the live wheel stops too
    assert not driver.read_status().motors_enabled
    with pytest.raises(DriverUnavailable):
        driver.set_velocity(Twist2D(0.2, 0.0))
    drives.right.restore()
    driver.connect()  # back: the drives are re-enabled and the fault cleared
    assert not driver.read_status().faults
    driver.set_velocity(Twist2D(0.1, 0.0))
    assert wait_for(lambda: drives.right.target != 0, 1.0)


def test_drive_fault_is_reported_and_reset_on_connect(
    rig: tuple[SimulatedDiffDrive, CanopenDriver],
) -> None:
    drives, driver = rig
    driver.connect()
    drives.left.inject_fault(0x2310)
    assert wait_for(lambda: any("EMCY 0x2310" in f for f in driver.read_status().faults), 1.0)
    assert driver.stats.emcys == 1
    driver.connect()
    assert drives.left.state == SW_OPERATION_ENABLED
    assert drives.left.node.sdo[0x603F].raw == 0
    assert not driver.read_status().faults


def test_close_twice_leaves_drives_stopped_and_disabled(
    rig: tuple[SimulatedDiffDrive, CanopenDriver],
) -> None:
    drives, driver = rig
    driver.connect()
    driver.set_velocity(Twist2D(0.2, 0.0))
    driver.close()
    driver.close()
    assert wait_for(lambda: all(d.target == 0 for d in drives.drives), 1.0)
    assert all(d.state != SW_OPERATION_ENABLED for d in drives.drives)
    with pytest.raises(DriverError):
        driver.set_velocity(Twist2D(0.1, 0.0))


def test_non_finite_command_is_refused(rig: tuple[SimulatedDiffDrive, CanopenDriver]) -> None:
    _, driver = rig
    driver.connect()
    with pytest.raises(ValueError, match="non-finite"):
        driver.set_velocity(Twist2D(math.inf, 0.0))


def test_absent_drives_give_a_clear_error() -> None:
    settings = CanopenSettings(interface="virtual", channel="nobody-here", connect_timeout_s=0.3)
    driver = CanopenDriver(settings, robot=ROBOT)
    try:
        with pytest.raises(DriverUnavailable, match="left drive"):
            driver.connect()
    finally:
        driver.close()


def _vcan0_present() -> bool:
    try:
        can.Bus(interface="socketcan", channel="vcan0").shutdown()
    except (OSError, can.CanError):
        return False
    return True


@pytest.mark.skipif(not _vcan0_present(), reason="needs SocketCAN vcan0 (modprobe vcan; root)")
def test_runs_on_socketcan_vcan() -> None:
    with SimulatedDiffDrive("vcan0", interface="socketcan") as drives:
        driver = CanopenDriver(CanopenSettings(interface="socketcan", channel="vcan0"), robot=ROBOT)
        try:
            driver.connect()
            driver.set_velocity(Twist2D(0.1, 0.0))
            assert wait_for(lambda: drives.left.target != 0, 1.0)
        finally:
            driver.close()
