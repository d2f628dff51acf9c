"""The ARCOS emulator as firmware: a raw client (no driver) sends each motion command ARIA
uses and reads the SIPs back; the robot moves as a P3DX's firmware moves it."""

from __future__ import annotations

import itertools
import logging
import math
import re
import socket
import time
from collections.abc import Iterator

import pytest

from phalanx.core.config_files import load_robot
from phalanx.drivers.arcos_tracker import ArcosStats, SipTracker
from phalanx.protocols.arcos import (
    SYNC0,
    SYNC1,
    SYNC2,
    Cmd,
    FrameParser,
    RobotConfig,
    command,
    decode_config,
    factors_for,
    vel2_arg,
)
from phalanx.simulator.arcos_emulator import ArcosEmulator, EmulatorOptions, TcpLink

pytestmark = pytest.mark.drivers
ROBOT = load_robot("p3dx")


class Client:
    """ARCOS by hand: sync, open, enable; send commands; read SIPs as the driver does."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port))
        self.sock.settimeout(0.005)
        self.parser = FrameParser()
        self.tracker = SipTracker(ArcosStats())
        self.tracker.factors = factors_for("p3dx-sh")
        self.config: RobotConfig | None = None
        self.pulsed_s = time.monotonic()
        for step in (SYNC0, SYNC1, SYNC2):
            self.send(step)
            self.pump(0.1)
        for cmd, arg in ((Cmd.OPEN, None), (Cmd.CONFIG, None), (Cmd.ENABLE, 1)):
            self.send(cmd, arg)
        self.pump(0.3)

    def send(self, cmd: int, arg: int | None = None) -> None:
        self.sock.sendall(command(cmd, arg))
        self.pulsed_s = time.monotonic()

    def pump(self, seconds: float) -> None:
        """Read for `seconds`, sending a PULSE every 0.4 s (the firmware watchdog is 2 s)."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            if time.monotonic() - self.pulsed_s > 0.4:
                self.send(Cmd.PULSE)
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            for body in self.parser.feed(data):
                if body[0] == 0x20:
                    self.config = decode_config(body)
                else:
                    self.tracker.take(body, byte_time_s=0.0)

    @property
    def pose(self) -> tuple[float, float, float]:
        """mm, mm, deg since the first SIP."""
        assert self.tracker.odometry is not None
        p = self.tracker.odometry.pose
        return p.x_m * 1000.0, p.y_m * 1000.0, math.degrees(p.theta_rad)

    @property
    def speed(self) -> tuple[float, float]:
        """mm/s, deg/s."""
        assert self.tracker.odometry is not None
        t = self.tracker.odometry.twist
        return t.v_mps * 1000.0, math.degrees(t.omega_radps)

    def at_rest(self, timeout_s: float = 10.0) -> None:
        deadline = time.monotonic() + timeout_s
        self.pump(0.3)
        while self.speed != (0.0, 0.0) and time.monotonic() < deadline:
            self.pump(0.1)
        self.pump(0.2)


@pytest.fixture
def emulator() -> Iterator[ArcosEmulator]:
    with ArcosEmulator(TcpLink(0), ROBOT) as emulator:
        yield emulator


@pytest.fixture
def client(emulator: ArcosEmulator) -> Iterator[Client]:
    client = Client(emulator.link.port)  # type: ignore[attr-defined]
    try:
        yield client
    finally:
        client.sock.close()


def test_vel2_with_negative_wheels_drives_backwards(client: Client) -> None:
    client.send(Cmd.VEL2, vel2_arg(-10, -10))  # ARIA's setVel2(-200, -200)
    client.pump(2.0)
    client.send(Cmd.STOP)
    client.at_rest()
    x, y, th = client.pose
    # 2 s at -200 mm/s (ramps at 300 mm/s^2 in and out cancel out): 0.4 m backwards.
    assert x == pytest.approx(-400.0, abs=15.0)
    assert abs(y) < 1.0
    assert abs(th) < 0.1


def test_vel2_turns_towards_the_faster_wheel(client: Client) -> None:
    client.send(Cmd.VEL2, vel2_arg(-5, 5))  # -100 and +100 mm/s
    client.pump(0.8)
    v, w = client.speed
    # (right - left) / 2 * DiffConvFactor 0.0056 = 0.56 rad/s = 32.1 deg/s
    assert v == 0.0
    assert w == pytest.approx(32.1, abs=0.2)


def test_head_and_dhead_turn_to_their_heading(client: Client) -> None:
    client.send(Cmd.HEAD, 90)
    client.at_rest()
    assert client.pose[2] == pytest.approx(90.0, abs=0.3)
    client.send(Cmd.DHEAD, -45)
    client.at_rest()
    assert client.pose[2] == pytest.approx(45.0, abs=0.3)
    client.send(Cmd.HEAD, -90)  # the short way round, clockwise
    client.pump(0.5)
    assert client.speed[1] < 0.0
    client.at_rest()
    assert client.pose[2] == pytest.approx(-90.0, abs=0.3)


@pytest.mark.parametrize(("cmd", "arg"), [(Cmd.HEAD, 90), (Cmd.MOVE, 600)])
def test_an_emulator_woken_late_catches_up_in_its_cycles_steps(
    client: Client, emulator: ArcosEmulator, cmd: int, arg: int
) -> None:
    # Its thread held up 0.3 s at a time in mid-motion, as a loaded machine holds it up:
    # a turn to a heading or a move ends where it does on time (a catch-up made in one
    # step overshot the heading, or stopped short of the distance).
    client.send(cmd, arg)
    client.pump(0.2)
    for _ in range(6):
        with emulator._lock:  # (the firmware's own: its thread waits for it)
            time.sleep(0.3)
        client.pump(0.05)
    client.at_rest()
    x, y, th = client.pose
    if cmd == Cmd.HEAD:
        assert th == pytest.approx(90.0, abs=0.3)
    else:
        assert math.hypot(x, y) == pytest.approx(600.0, abs=3.0)


def test_a_late_emulator_sends_the_cycles_it_missed_each_as_it_was(
    client: Client, emulator: ArcosEmulator
) -> None:
    # Held up 0.35 s while driving at 200 mm/s, it sends the SIPs of the cycles it
    # missed at once, each with the robot where it was at its cycle (20 mm apart), as
    # firmware on its own clock does; the driver stamps them on that cycle
    # (CycleClock). Before, one SIP went out late with the robot where it was then.
    client.send(Cmd.VEL, 200)
    client.pump(1.5)  # at speed
    before = client.tracker.stats.sips
    with emulator._lock:
        time.sleep(0.35)
    xs = []
    deadline = time.monotonic() + 2.0
    while client.tracker.stats.sips < before + 6 and time.monotonic() < deadline:
        try:
            data = client.sock.recv(65536)
        except TimeoutError:
            continue
        for body in client.parser.feed(data):
            if client.tracker.take(body, byte_time_s=0.0) is not None:
                xs.append(client.pose[0])
    client.send(Cmd.STOP)
    steps = [b - a for a, b in itertools.pairwise(xs)]
    assert len(steps) >= 5, xs
    assert steps == pytest.approx([20.0] * len(steps), abs=1.5), xs


def test_move_goes_its_distance_along_the_heading_and_stops(client: Client) -> None:
    client.send(Cmd.DHEAD, 30)
    client.at_rest()
    client.send(Cmd.MOVE, 600)
    client.at_rest()
    x, y, th = client.pose
    assert math.hypot(x, y) == pytest.approx(600.0, abs=3.0)
    assert math.degrees(math.atan2(y, x)) == pytest.approx(th, abs=0.2)
    client.send(Cmd.MOVE, -250)
    client.at_rest()
    assert math.hypot(*client.pose[:2]) == pytest.approx(350.0, abs=3.0)


def test_setv_and_setrv_cap_the_speeds_and_the_tops_cap_them(
    client: Client, emulator: ArcosEmulator
) -> None:
    client.send(Cmd.SETV, 150)
    client.send(Cmd.SETRV, 20)
    client.send(Cmd.VEL, 300)
    client.send(Cmd.RVEL, 40)
    client.pump(1.5)
    assert client.speed == pytest.approx((150.0, 20.0), abs=0.2)
    client.send(Cmd.SETV, 9000)  # above TransVelTop: capped there
    client.send(Cmd.CONFIG)
    client.pump(0.3)
    assert client.config is not None
    assert client.config.trans_vel_max_mmps == client.config.trans_vel_top_mmps == 1200
    assert client.config.rot_vel_max_degps == 20
    assert emulator.limits.trans_vel_max == 1200.0


def _ramp_time_s(client: Client, target_mmps: float) -> float:
    started = time.monotonic()
    client.send(Cmd.VEL, round(target_mmps))
    while client.speed[0] < target_mmps and time.monotonic() - started < 5.0:
        client.pump(0.02)
    return time.monotonic() - started


def test_seta_and_setra_set_the_ramps(client: Client, emulator: ArcosEmulator) -> None:
    slow = _ramp_time_s(client, 300.0)  # 300 mm/s^2: 1 s
    client.send(Cmd.VEL, 0)
    client.at_rest()
    client.send(Cmd.SETA, 900)
    fast = _ramp_time_s(client, 300.0)  # 0.33 s
    assert slow == pytest.approx(1.0, abs=0.15)
    assert fast == pytest.approx(1.0 / 3.0, abs=0.15)
    client.send(Cmd.SETA, -600)
    client.send(Cmd.SETRA, 50)
    client.send(Cmd.SETRA, -80)
    client.pump(0.2)
    lim = emulator.limits
    assert (lim.trans_accel, lim.trans_decel, lim.rot_accel, lim.rot_decel) == (900, 600, 50, 80)


def _stopping_time_s(client: Client, cmd: Cmd) -> float:
    client.send(Cmd.VEL, 300)
    client.pump(1.5)
    started = time.monotonic()
    client.send(cmd)
    while client.speed[0] > 0.0 and time.monotonic() - started < 5.0:
        client.pump(0.01)
    return time.monotonic() - started


def test_e_stop_overrides_the_deceleration_and_then_lets_go(client: Client) -> None:
    stop_s = _stopping_time_s(client, Cmd.STOP)  # 300 mm/s at 300 mm/s^2: 1 s
    client.at_rest()
    estop_s = _stopping_time_s(client, Cmd.E_STOP)  # at the top, 1000 mm/s^2: 0.3 s
    assert stop_s == pytest.approx(1.0, abs=0.15)
    assert estop_s < 0.45
    client.at_rest()
    client.send(Cmd.VEL, 200)  # this firmware does not latch an E_STOP (nor AMRISim's)
    client.pump(1.0)
    assert client.speed[0] > 100.0


def test_seto_puts_the_odometry_origin_where_the_robot_is(client: Client) -> None:
    client.send(Cmd.VEL, 300)
    client.pump(1.0)
    client.send(Cmd.STOP)
    client.at_rest()
    assert client.pose[0] > 100.0
    client.send(Cmd.SETO)
    client.pump(0.3)
    sip = client.tracker.sip
    assert sip is not None
    assert (sip.x, sip.y, sip.th) == (0, 0, 0)


def test_a_command_acts_from_the_moment_it_arrives(client: Client) -> None:
    """Not from the SIP tick before it (which moved the robot up to 100 ms early)."""
    client.send(Cmd.SETA, 1000)
    client.pump(0.2)
    sips = client.tracker.stats.sips
    while client.tracker.stats.sips == sips:  # a SIP just went out
        client.pump(0.002)
    time.sleep(0.05)  # mid-cycle
    x0 = client.pose[0]
    sent = time.monotonic()
    client.send(Cmd.VEL, 300)
    odometry = client.tracker.odometry
    while odometry is None or odometry.stamp_s < sent + 0.4:
        client.pump(0.002)
        odometry = client.tracker.odometry
    t = odometry.stamp_s - sent  # the SIP's arrival (no time on the wire over loopback)
    # 0.3 s ramping at 1 m/s^2 (45 mm), then 0.3 m/s; from the tick before: +15 mm
    expected_mm = 45.0 + 300.0 * (t - 0.3)
    assert client.pose[0] - x0 == pytest.approx(expected_mm, abs=5.0)


def test_the_config_packet_carries_a_p3dxs_values(client: Client) -> None:
    config = client.config
    assert config is not None
    assert (config.robot_type, config.subtype, config.name) == ("Pioneer", "p3dx-sh", "phalanx-emu")
    assert (config.trans_vel_max_mmps, config.rot_vel_max_degps) == (1200, 300)
    assert (config.trans_accel_mmps2, config.trans_decel_mmps2) == (300, 300)
    assert (config.rot_accel_degps2, config.rot_decel_degps2) == (100, 100)
    assert (config.trans_vel_top_mmps, config.rot_vel_top_degps) == (1200, 300)
    assert config.trans_accel_top_mmps2 >= config.trans_decel_mmps2
    assert (config.watchdog_ms, config.sip_cycle_ms) == (2000, 100)
    assert config.low_battery_dv == 110
    assert client.tracker.status(link_fault="", estop="").battery_v == pytest.approx(12.5)


def test_the_watchdog_says_how_long_it_heard_nothing(caplog: pytest.LogCaptureFixture) -> None:
    with (
        caplog.at_level(logging.WARNING, logger="phalanx.emulator"),
        ArcosEmulator(TcpLink(0), ROBOT, EmulatorOptions(watchdog_s=0.3)) as emulator,
    ):
        client = Client(emulator.link.port)  # type: ignore[attr-defined]
        try:
            deadline = time.monotonic() + 2.0
            while not emulator.stats.watchdog_stops and time.monotonic() < deadline:
                time.sleep(0.02)
        finally:
            client.sock.close()
    lines = [r.getMessage() for r in caplog.records if "watchdog" in r.getMessage()]
    assert lines
    for line in lines:  # the silence (0.3 s and a loop step), not the monotonic clock
        silence_s = float(re.search(r"no packet for ([\d.]+) s", line).group(1))  # type: ignore[union-attr]
        assert 0.3 <= silence_s <= 0.5, line
