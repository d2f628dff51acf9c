"""ARCOS link faults (the fault tier): SIPs that stop, or arrive garbled, while the link
still carries commands; a robot that goes silent while the driver reconnects. A control
loop runs throughout as an agent's does (a command and both reads every 50 ms) and
keeps asking for motion. Checked: STOP reaches the robot within 0.2 s of the driver
declaring the SIPs lost; the motors stay stopped until SIPs are back and a command asks
for motion; no control call waits longer than one control period, reconnecting or not.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import pytest

from phalanx.core.config_files import load_robot
from phalanx.core.errors import DriverError
from phalanx.core.geometry import Twist2D
from phalanx.drivers.arcos import ArcosDriver, ArcosSettings
from phalanx.simulator.arcos_emulator import ArcosEmulator, Link, PtyLink, TcpLink

pytestmark = pytest.mark.drivers
ROBOT = load_robot("p3dx")
PERIOD_S = 0.05  # the paper scenario's control period
ASK = Twist2D(0.2, 0.0)


@dataclass
class Loop:
    """What a control loop saw, step by step."""

    longest_call_s: float = 0.0
    refused: int = 0
    steps: list[tuple[float, bool, Twist2D]] = field(default_factory=list)  # t, link, target


def _control(
    driver: ArcosDriver, robot: ArcosEmulator, until: Callable[[], bool], limit_s: float
) -> Loop:
    """Command ASK and read both readings every PERIOD_S until `until()`; time each call."""
    loop = Loop()
    deadline = time.monotonic() + limit_s
    while not until():
        assert time.monotonic() < deadline, "the link never came back"
        for call in (driver.read_odometry, driver.read_status, lambda: driver.set_velocity(ASK)):
            started = time.monotonic()
            try:
                call()
            except DriverError:
                loop.refused += 1
            loop.longest_call_s = max(loop.longest_call_s, time.monotonic() - started)
        loop.steps.append((time.monotonic(), driver.link_up, robot.target))
        time.sleep(PERIOD_S)
    return loop


@pytest.fixture(params=["tcp", "pty"])
def rig(request: pytest.FixtureRequest) -> Iterator[tuple[ArcosEmulator, ArcosDriver]]:
    """A robot driving at 0.2 m/s under a driver, over TCP or a pseudo-terminal."""
    link: Link = TcpLink(0) if request.param == "tcp" else PtyLink()
    with ArcosEmulator(link, ROBOT) as robot:
        where = (
            {"tcp": f"127.0.0.1:{link.port}"}  # type: ignore[attr-defined]
            if request.param == "tcp"
            else {"port": link.device}  # type: ignore[attr-defined]
        )
        settings = ArcosSettings(**where, connect_timeout_s=0.5, sync_retries=1)  # type: ignore[arg-type]
        with ArcosDriver(settings, robot=ROBOT) as driver:
            driver.set_velocity(ASK)
            deadline = time.monotonic() + 3.0
            while robot.body.state().twist.v_mps < 0.15 and time.monotonic() < deadline:
                driver.set_velocity(ASK)
                time.sleep(PERIOD_S)
            yield robot, driver


def _check(robot: ArcosEmulator, driver: ArcosDriver, loop: Loop) -> None:
    stats = driver.stats
    assert stats.links_lost >= 1
    assert stats.sips_lost_s is not None
    stop_s = robot.stats.first_after("STOP", stats.sips_lost_s)
    assert stop_s is not None, "no STOP reached the robot"
    assert 0.0 <= stop_s - stats.sips_lost_s < 0.2
    # From the STOP until the link is back, the robot's firmware aims at rest, though the
    # loop asked for 0.2 m/s at every step (and was refused).
    held = [target for t, up, target in loop.steps if t > stop_s + 0.01 and not up]
    assert held
    assert all(target == Twist2D(0.0, 0.0) for target in held), held
    assert loop.refused > 0
    assert loop.longest_call_s < PERIOD_S


def _moves_again_when_asked(robot: ArcosEmulator, driver: ArcosDriver) -> None:
    time.sleep(0.3)  # SIPs are back, nobody asked for motion: still at rest
    assert robot.target == Twist2D(0.0, 0.0)
    assert robot.body.state().twist == Twist2D(0.0, 0.0)
    driver.set_velocity(ASK)
    time.sleep(0.1)
    assert robot.target == ASK


def test_sips_that_stop_while_commands_flow_stop_the_robot_at_once(
    rig: tuple[ArcosEmulator, ArcosDriver],
) -> None:
    robot, driver = rig
    robot.drop_sips(25)  # 2.5 s without SIPs; commands still reach the robot
    loop = _control(driver, robot, lambda: driver.stats.reconnects >= 1, 15.0)
    _check(robot, driver, loop)
    _moves_again_when_asked(robot, driver)


def test_garbled_sips_stop_the_robot_at_once(rig: tuple[ArcosEmulator, ArcosDriver]) -> None:
    robot, driver = rig
    robot.garble_for(2.5)  # every byte the robot sends for 2.5 s is corrupt
    loop = _control(driver, robot, lambda: driver.stats.reconnects >= 1, 15.0)
    _check(robot, driver, loop)
    assert driver.parser.stats.bad_checksums + driver.parser.stats.garbage_bytes > 0
    _moves_again_when_asked(robot, driver)


def test_reconnecting_to_a_silent_robot_never_blocks_a_control_step(
    rig: tuple[ArcosEmulator, ArcosDriver],
) -> None:
    robot, driver = rig
    robot.unplug()  # silence both ways: every reconnect attempt waits out its timeouts
    started = time.monotonic()
    loop = _control(driver, robot, lambda: time.monotonic() - started > 4.0, 10.0)
    assert driver.stats.reconnect_failures >= 2  # attempts ran meanwhile
    assert not driver.link_up
    assert loop.longest_call_s < PERIOD_S
    robot.unplug(False)
    _control(driver, robot, lambda: driver.link_up, 15.0)
    _moves_again_when_asked(robot, driver)
