"""CAN link faults against the CiA 402 backend on python-can's virtual bus, with the
simulated drives: a hostile node flooding the bus with garbage (any id, any length:
forged EMCYs, short and absurd TPDOs, odd heartbeats), a drive that reboots mid-run,
both drives falling silent, and the same faults under a running agent. The driver never
raises anything but a DriverError, never integrates an absurd reading, stops both wheels
when it must, keeps its fault list bounded, and comes back on `connect()`.
"""

from __future__ import annotations

import math
import random
import threading
import time
from collections.abc import Iterator

import can
import pytest
from agentlab import agent_on_driver
from fleetlab import wait_for

from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_robot, load_scenario
from phalanx.core.errors import DriverError
from phalanx.core.geometry import Twist2D
from phalanx.core.limits import run_limits, safety_limits
from phalanx.core.states import State
from phalanx.drivers.canopen import MAX_FAULTS, CanopenDriver, CanopenSettings
from phalanx.drivers.safety import SafeDriver
from phalanx.runtime.clock import EpochClock
from phalanx.runtime.robot_io import DriverIO
from phalanx.simulator.cia402 import SimulatedDiffDrive

pytestmark = pytest.mark.drivers
ROBOT = load_robot("p3dx")
WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
STOP_S = 0.5  # a fault brings both wheel targets to zero within this


@pytest.fixture
def rig(request: pytest.FixtureRequest) -> Iterator[tuple[SimulatedDiffDrive, CanopenDriver, str]]:
    channel = f"fault-{request.node.name}"
    with SimulatedDiffDrive(channel) as drives:
        driver = CanopenDriver(CanopenSettings(interface="virtual", channel=channel), robot=ROBOT)
        try:
            driver.connect()
            yield drives, driver, channel
        finally:
            driver.close()


def _garbage(channel: str, n: int, seed: int) -> None:
    """`n` frames of any id and length, most on the drives' own ids."""
    rng = random.Random(seed)
    ids = [0x000, 0x080, 0x081, 0x082, 0x181, 0x182, 0x581, 0x582, 0x701, 0x702]
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        for _ in range(n):
            cid = rng.choice(ids) if rng.random() < 0.8 else rng.randrange(0x800)
            data = bytes(rng.randrange(256) for _ in range(rng.randrange(9)))
            bus.send(can.Message(arbitration_id=cid, data=data, is_extended_id=False))
    finally:
        bus.shutdown()


def _jam_sdo(channel: str, duration_s: float, jams: list[int]) -> None:
    """For `duration_s`, answer every SDO request to either drive at once with a
    response of a command byte no transfer expects (0xAC), racing the drive's own."""
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            msg = bus.recv(timeout=0.01)
            if msg is not None and msg.arbitration_id in (0x601, 0x602):
                answer = bytes([0xAC, *msg.data[1:4], 0, 0, 0, 0])
                bus.send(can.Message(arbitration_id=msg.arbitration_id - 0x80, data=answer))
                jams.append(msg.arbitration_id)
    finally:
        bus.shutdown()


def _stopped(drives: SimulatedDiffDrive) -> bool:
    return all(d.target == 0 for d in drives.drives)


def test_garbage_on_the_bus_stops_the_robot_safely_and_connect_brings_it_back(
    rig: tuple[SimulatedDiffDrive, CanopenDriver, str],
) -> None:
    drives, driver, channel = rig
    driver.set_velocity(Twist2D(0.2, 0.0))
    assert wait_for(lambda: abs(drives.left.velocity) > 1000, 2.0, poll_s=0.005)
    sent = time.monotonic()
    _garbage(channel, 3000, seed=7)
    assert wait_for(
        lambda: bool(driver.read_status().faults), 1.0, poll_s=0.005
    )  # forged EMCYs etc.
    assert wait_for(lambda: _stopped(drives), STOP_S, poll_s=0.005)
    assert time.monotonic() - sent < 5.0
    status, odometry = driver.read_status(), driver.read_odometry()
    assert len(status.faults) <= MAX_FAULTS  # an EMCY flood does not grow it for ever
    assert not status.motors_enabled
    for value in (odometry.pose.x_m, odometry.pose.y_m, odometry.twist.v_mps):
        assert math.isfinite(value)
    assert abs(odometry.twist.v_mps) <= ROBOT.wheel_v_max_mps  # no absurd reading went in
    assert abs(odometry.pose.x_m) < 5.0  # (a few seconds at 0.2 m/s)
    with pytest.raises(DriverError):  # refused while faulted: never an other exception
        driver.set_velocity(Twist2D(0.2, 0.0))
    driver.connect()  # the bus thread lived through it: the robot drives again
    assert not driver.read_status().faults
    driver.set_velocity(Twist2D(0.1, 0.0))
    assert wait_for(lambda: drives.left.target != 0, 1.0, poll_s=0.005)


def test_connect_outlasts_garbled_sdo_answers_for_up_to_its_timeout(
    request: pytest.FixtureRequest, caplog: pytest.LogCaptureFixture
) -> None:
    """Garbled SDO answers arriving for a second (a burst a slow bus thread is still
    working through) cost retries of the enabling sequence, not the connect: it gives up
    only after `connect_timeout_s`."""
    channel = f"fault-{request.node.name}"
    with SimulatedDiffDrive(channel) as drives:
        driver = CanopenDriver(CanopenSettings(interface="virtual", channel=channel), robot=ROBOT)
        jams: list[int] = []
        jammer = threading.Thread(target=_jam_sdo, args=(channel, 1.0, jams))
        try:
            jammer.start()
            time.sleep(0.05)  # the jammer listens before the first request
            with caplog.at_level("WARNING", logger="phalanx.canopen"):
                driver.connect()
            retries = [r for r in caplog.records if r.getMessage().endswith("; again")]
            assert len(retries) >= 3, (len(jams), [r.getMessage() for r in retries])
            driver.set_velocity(Twist2D(0.1, 0.0))
            assert wait_for(lambda: drives.left.target != 0, 1.0, poll_s=0.005)
        finally:
            jammer.join(timeout=5.0)
            driver.close()
    assert not jammer.is_alive()


def test_a_drive_that_reboots_mid_run_stops_both_wheels(
    rig: tuple[SimulatedDiffDrive, CanopenDriver, str],
) -> None:
    drives, driver, channel = rig
    driver.set_velocity(Twist2D(0.2, 0.0))
    assert wait_for(lambda: drives.left.target != 0, 1.0, poll_s=0.005)
    bus = can.Bus(interface="virtual", channel=channel)
    try:  # the right drive's boot-up message: it lost power and restarted
        bus.send(can.Message(arbitration_id=0x702, data=b"\x00", is_extended_id=False))
    finally:
        bus.shutdown()
    assert wait_for(
        lambda: any("left OPERATIONAL" in f for f in driver.read_status().faults), 1.0, poll_s=0.005
    )
    assert wait_for(lambda: _stopped(drives), STOP_S, poll_s=0.005)
    driver.connect()
    assert not driver.read_status().faults


def test_both_drives_silent_stop_the_robot_within_the_heartbeat_timeout(
    rig: tuple[SimulatedDiffDrive, CanopenDriver, str],
) -> None:
    drives, driver, _ = rig
    driver.set_velocity(Twist2D(0.2, 0.0))
    assert wait_for(lambda: drives.left.target != 0, 1.0, poll_s=0.005)
    lost = time.monotonic()
    for drive in drives.drives:
        drive.lose_heartbeat()
    assert wait_for(lambda: len(driver.read_status().faults) == 2, 2.0, poll_s=0.005)
    assert time.monotonic() - lost < driver.settings.heartbeat_timeout_s + 0.2
    assert not driver.read_status().motors_enabled  # (a drive cut off stops on its own)
    with pytest.raises(DriverError):
        driver.set_velocity(Twist2D(0.2, 0.0))
    for drive in drives.drives:
        drive.restore()
    driver.connect()
    assert not driver.read_status().faults


def test_an_agent_on_a_faulted_can_robot_commands_zero_and_stays_within_limits(
    request: pytest.FixtureRequest,
) -> None:
    """The agent runtime over the safety wrapper: garbage on the bus mid-run puts the
    robot in FAULT on the next steps; every command it sent stayed within the run's
    limits, and its commands fall to zero."""
    scenario = apply_overrides(load_scenario(WEDGE), ["duration_s=30"])
    limits = run_limits(ROBOT, scenario.limits)
    channel = f"stack-{request.node.name}"
    sent: list[Twist2D] = []
    with SimulatedDiffDrive(channel) as drives:
        driver = CanopenDriver(CanopenSettings(interface="virtual", channel=channel), robot=ROBOT)
        safe = SafeDriver(driver, safety_limits(ROBOT, scenario.limits))
        with safe:
            clock = EpochClock(epoch_s=time.time() + 0.3, dt_s=scenario.dt_s, steps=300)
            io = DriverIO(safe, ROBOT, origin=scenario.start_pose("r1"))
            write = io.write
            io.write = lambda tick, command: (sent.append(command), write(tick, command))[1]  # type: ignore[method-assign]
            with agent_on_driver(scenario, ROBOT, io, clock, fleet="canfault") as runtime:
                assert wait_for(lambda: runtime.steps > 20, 10.0, poll_s=0.005)
                _garbage(channel, 2000, seed=11)
                assert wait_for(
                    lambda: (
                        runtime.last is not None and runtime.last.state.fsm_state == State.FAULT
                    ),
                    3.0,
                    poll_s=0.005,
                )
                assert wait_for(lambda: _stopped(drives), STOP_S, poll_s=0.005)
                steps = runtime.steps
                assert wait_for(lambda: runtime.steps > steps + 10, 5.0, poll_s=0.005)  # it goes on
    assert sent
    for command in sent:
        assert abs(command.v_mps) <= limits.v_max_mps + 1e-9
        assert abs(command.omega_radps) <= limits.omega_max_radps + 1e-9
    assert sent[-1] == Twist2D(0.0, 0.0)
