"""Our `arcos` driver against AMRISim's P3DX (firmware nobody here wrote): it reads the
robot's own limits from the CONFIG packet, reaches a commanded speed, integrates the same
odometry AMRISim says it sent, holds an E-stop that AMRISim forgets, and survives
AMRISim freezing (no SIPs while its socket still takes commands) and moving to another
port. Skipped unless PHALANX_AMRISIM gives the binary (docs/INTEROP.md)."""

from __future__ import annotations

import math
import sys
import time
from typing import Any

import pytest
from fleetlab import wait_for

from phalanx.core.config_files import load_robot
from phalanx.core.errors import DriverError
from phalanx.core.geometry import Twist2D
from phalanx.drivers.arcos import ArcosDriver, ArcosSettings

pytestmark = [pytest.mark.drivers, pytest.mark.integration]


def report(text: str) -> None:
    """Figures for docs/INTEROP.md (shown with `pytest -n 0 -s`: a worker keeps them)."""
    sys.stdout.write(f"{text}\n")


ROBOT = load_robot("p3dx")
Amrisim = Any  # the `amrisim` fixture's object (conftest.py)
DT_S = 0.05  # a control period (the paper scenario's)


def _drive(driver: ArcosDriver, twist: Twist2D, seconds: float) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        driver.set_velocity(twist)
        time.sleep(DT_S)


def _refused(driver: ArcosDriver, twist: Twist2D) -> str:
    """ "" if `twist` was sent, else the first word the refusal's message has of "link"."""
    try:
        driver.set_velocity(twist)
    except DriverError as exc:
        return "link" if "link" in str(exc) else str(exc)
    return ""


def test_the_driver_reads_amrisims_limits_and_reaches_0_3_mps(amrisim: Amrisim) -> None:
    with ArcosDriver(ArcosSettings(tcp=f"127.0.0.1:{amrisim.port}"), robot=ROBOT) as driver:
        config = driver.robot_config
        assert config is not None
        report(f"AMRISim CONFIG: {config}")
        assert (config.robot_type, config.subtype, config.name) == ("Pioneer", "p3dx", "AMRISim")
        assert config.trans_vel_max_mmps == 3000
        assert config.rot_vel_max_degps == 150
        assert config.watchdog_ms == 2000
        assert (config.trans_accel_mmps2, config.rot_accel_degps2) == (300, 100)
        assert driver.robot_limits() == pytest.approx((3.0, math.radians(150.0)))
        _drive(driver, Twist2D(0.3, 0.0), 2.5)  # 1 s to reach it at 0.3 m/s^2
        speed = driver.read_odometry().twist.v_mps
        report(f"commanded 0.3 m/s, AMRISim reports {speed:.4f} m/s")
        assert speed == pytest.approx(0.3, abs=0.002)
        assert driver.read_status().battery_v == pytest.approx(13.0)


def test_odometry_equals_what_amrisim_logged_sending(amrisim: Amrisim) -> None:
    with ArcosDriver(ArcosSettings(tcp=f"127.0.0.1:{amrisim.port}"), robot=ROBOT) as driver:
        _drive(driver, Twist2D(0.3, 0.0), 3.0)
        _drive(driver, Twist2D(0.2, math.radians(25.0)), 3.0)
        _drive(driver, Twist2D(-0.15, math.radians(-15.0)), 2.0)
        driver.stop()
        assert wait_for(lambda: driver.read_odometry().twist == Twist2D(0.0, 0.0), 3.0, poll_s=0.02)
        time.sleep(0.5)
        pose = driver.read_odometry().pose
    x_mm, y_mm, th_deg = amrisim.sent_sips()[-1]  # AMRISim's odometry (mm, mm, whole deg)
    got = (pose.x_m * 1000.0, pose.y_m * 1000.0, math.degrees(pose.theta_rad))
    report(f"driver odometry {got}; AMRISim's last SIP {(x_mm, y_mm, th_deg)}")
    assert math.hypot(x_mm, y_mm) > 800.0  # it went somewhere
    # A position count is 0.485 mm (p3dx). AMRISim reports whole degrees; the driver
    # follows them finer from the yaw rate, always inside the degree reported.
    assert got[0] == pytest.approx(x_mm, abs=1.0)
    assert got[1] == pytest.approx(y_mm, abs=1.0)
    assert got[2] == pytest.approx(th_deg, abs=0.5 + 1e-9)  # + a float's rounding


def test_an_estop_amrisim_forgets_is_held_by_the_driver(amrisim: Amrisim) -> None:
    with ArcosDriver(ArcosSettings(tcp=f"127.0.0.1:{amrisim.port}"), robot=ROBOT) as driver:
        _drive(driver, Twist2D(0.3, 0.0), 2.0)
        driver.estop()
        assert wait_for(lambda: driver.read_odometry().twist.v_mps == 0.0, 2.0, poll_s=0.02)
        time.sleep(0.5)
        sip = driver.readings.sip
        assert sip is not None
        assert not sip.estopped  # AMRISim does not report (or latch) an E-stop
        assert driver.read_status().estopped  # the driver does
        with pytest.raises(Exception, match="E-stopped"):
            driver.set_velocity(Twist2D(0.3, 0.0))
        time.sleep(1.0)
        assert driver.read_odometry().twist.v_mps == 0.0
        driver.connect()  # the deliberate reset
        assert not driver.read_status().estopped
        _drive(driver, Twist2D(0.2, 0.0), 1.5)
        assert driver.read_odometry().twist.v_mps > 0.1


def test_a_frozen_amrisim_is_stopped_and_found_again_on_its_new_port(amrisim: Amrisim) -> None:
    """SIGSTOP: no SIPs, though AMRISim's socket still takes bytes. The driver sends STOP
    at once and reconnects on its own thread (never blocking a control step); AMRISim,
    thawed, takes the STOP, drops the old connection and listens on the next port, where
    the driver's fallbacks find it; the robot stays at rest until motion is asked for."""
    port = amrisim.port
    settings = ArcosSettings(
        tcp=f"127.0.0.1:{port}",
        fallbacks=tuple(f"127.0.0.1:{port + i}" for i in range(1, 4)),
        connect_timeout_s=1.0,
        sync_retries=1,
    )
    longest = 0.0
    with ArcosDriver(settings, robot=ROBOT) as driver:
        _drive(driver, Twist2D(0.3, 0.0), 2.0)
        amrisim.pause(True)
        frozen_s = time.monotonic()
        while time.monotonic() - frozen_s < 4.0 or not driver.link_up:
            if time.monotonic() - frozen_s > 3.0:
                amrisim.pause(False)
            started = time.monotonic()
            driver.read_odometry()
            driver.read_status()
            refused = _refused(driver, Twist2D(0.3, 0.0))  # the agent keeps asking
            assert refused in ("", "link"), refused
            longest = max(longest, time.monotonic() - started)
            assert time.monotonic() - frozen_s < 30.0, "never reconnected"
            time.sleep(DT_S)
        stats = driver.stats
        assert stats.sips_lost_s is not None
        assert stats.loss_stop_s is not None
        report(
            f"lost at +{stats.sips_lost_s - frozen_s:.2f} s, STOP sent "
            f"{stats.loss_stop_s - stats.sips_lost_s:.4f} s later; back on {driver.address}; "
            f"longest control call {longest * 1000:.1f} ms"
        )
        assert stats.loss_stop_s - stats.sips_lost_s < 0.2
        assert driver.address != f"127.0.0.1:{port}"  # AMRISim moved; the driver followed
        assert longest < DT_S
        time.sleep(1.0)
        assert abs(driver.read_odometry().twist.v_mps) < 0.005  # at rest until asked
        _drive(driver, Twist2D(0.2, 0.0), 1.5)
        assert driver.read_odometry().twist.v_mps > 0.1
