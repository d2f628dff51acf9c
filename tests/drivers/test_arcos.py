"""ARCOS: byte-exact framing, a parser that survives anything, and the driver against the
robot emulator over a real pty and real TCP, with faults injected."""

from __future__ import annotations

import math
import os
import random
import time
from collections.abc import Iterator

import pytest
from fleetlab import wait_for
from hypothesis import given, settings
from hypothesis import strategies as st

from phalanx.core.config_files import load_robot
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.limits import SafetyLimits
from phalanx.core.motion import Body
from phalanx.drivers.arcos import ArcosDriver, ArcosSettings
from phalanx.drivers.arcos_link import byte_time_s
from phalanx.drivers.safety import SafeDriver
from phalanx.protocols.arcos import (
    Cmd,
    FrameParser,
    Sip,
    checksum,
    command,
    decode_sip,
    encode_sip,
    frame,
    wrap_delta,
)
from phalanx.protocols.arcos_config import FIELDS
from phalanx.simulator.arcos_emulator import ArcosEmulator, EmulatorOptions, PtyLink, TcpLink

pytestmark = pytest.mark.drivers
ROBOT = load_robot("p3dx")

# Test vectors: command frames, byte for byte.
VECTORS = [
    (Cmd.PULSE, None, "FA FB 03 00 00 00"),
    (Cmd.OPEN, None, "FA FB 03 01 00 01"),
    (Cmd.CLOSE, None, "FA FB 03 02 00 02"),
    (Cmd.ENABLE, 1, "FA FB 06 04 3B 01 00 05 3B"),
    (Cmd.VEL, 300, "FA FB 06 0B 3B 2C 01 37 3C"),
    (Cmd.VEL, -300, "FA FB 06 0B 1B 2C 01 37 1C"),
    (Cmd.RVEL, -45, "FA FB 06 15 1B 2D 00 42 1B"),
    (Cmd.STOP, None, "FA FB 03 1D 00 1D"),
    (Cmd.E_STOP, None, "FA FB 03 37 00 37"),
]


@pytest.mark.parametrize(("cmd", "arg", "expected"), VECTORS)
def test_command_frames_are_byte_exact(cmd: Cmd, arg: int | None, expected: str) -> None:
    assert command(cmd, arg) == bytes.fromhex(expected)
    assert list(FrameParser().feed(bytes.fromhex(expected))) == [bytes.fromhex(expected)[3:-2]]


def test_checksum_xors_an_odd_last_byte() -> None:
    assert checksum(b"\x01\x02\x03") == (0x0102 ^ 0x03)
    assert checksum(b"") == 0


_tails = st.one_of(
    st.just({}),
    st.fixed_dictionaries(
        {
            "rot_vel_x10": st.integers(-3000, 3000),
            "battery_tail_dv": st.integers(0, 300),
            "fault_flags": st.none() | st.integers(0, 0xFFFF),
        }
    ),
)
sips = _tails.flatmap(
    lambda tail: st.builds(
        Sip,
        moving=st.booleans(),
        x=st.integers(0, 0x7FFF),
        y=st.integers(0, 0x7FFF),
        th=st.integers(-2048, 2047),
        left_vel=st.integers(-2000, 2000),
        right_vel=st.integers(-2000, 2000),
        battery_dv=st.integers(0, 255),
        stall_bumpers=st.integers(0, 0xFFFF),
        flags=st.integers(0, 0xFFFF),
        sonars=st.lists(st.tuples(st.integers(0, 15), st.integers(0, 5000)), max_size=16).map(
            tuple
        ),
        **{k: st.just(v) for k, v in tail.items()},
    )
)


@given(sips)
def test_sip_round_trips(sip: Sip) -> None:
    (body,) = FrameParser().feed(encode_sip(sip))
    assert decode_sip(body) == sip


@given(st.lists(st.tuples(st.binary(max_size=40), sips), min_size=1, max_size=8), st.data())
@settings(max_examples=200)
def test_parser_recovers_every_frame_from_garbage_and_splits(
    chunks: list[tuple[bytes, Sip]], data: st.DataObject
) -> None:
    """Garbage between frames (any bytes, even fake headers) costs at most the frames
    it overlaps: every frame preceded by header-free garbage is recovered exactly."""
    stream = bytearray()
    expected = []
    for junk, sip in chunks:
        clean = junk.replace(b"\xfa", b"")  # junk without a header byte cannot fake a frame
        stream += clean + encode_sip(sip)
        expected.append(encode_sip(sip)[3:-2])
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=6)))
    parser = FrameParser()
    got = []
    for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        got += list(parser.feed(bytes(stream[a:b])))
    assert got == expected


@given(st.binary(max_size=2000))
def test_parser_never_raises_and_only_yields_checksummed_frames(noise: bytes) -> None:
    for body in FrameParser().feed(noise):
        assert frame(body)[3:-2] == body  # re-framing reproduces it: checksum was valid


def test_bad_checksum_and_bad_length_are_counted_and_skipped() -> None:
    good = command(Cmd.STOP)
    corrupt = bytearray(command(Cmd.VEL, 300))
    corrupt[-1] ^= 0xFF
    parser = FrameParser()
    got = list(parser.feed(b"\x00\x11" + bytes(corrupt) + b"\xfa\xfb\xff" + good))
    assert got == [good[3:-2]]
    assert parser.stats.bad_checksums == 1
    assert parser.stats.bad_lengths == 1
    assert parser.stats.garbage_bytes >= 2


def test_position_counters_unwrap_across_the_15_bit_boundary() -> None:
    assert wrap_delta(5, 0x7FFB) == 10
    assert wrap_delta(0x7FFB, 5) == -10
    assert wrap_delta(300, 100) == 200


# -- the driver against the emulator ---------------------------------------------------


@pytest.fixture
def pty_emulator() -> Iterator[ArcosEmulator]:
    with ArcosEmulator(PtyLink(), ROBOT) as emulator:
        yield emulator


@pytest.fixture
def tcp_emulator() -> Iterator[ArcosEmulator]:
    with ArcosEmulator(TcpLink(0), ROBOT) as emulator:
        yield emulator


def _tcp(emulator: ArcosEmulator, **kw: object) -> ArcosSettings:
    return ArcosSettings(tcp=f"127.0.0.1:{emulator.link.port}", **kw)  # type: ignore[attr-defined]


def test_handshake_reads_name_subtype_and_limits(pty_emulator: ArcosEmulator) -> None:
    with ArcosDriver(ArcosSettings(port=pty_emulator.link.device), robot=ROBOT) as driver:  # type: ignore[attr-defined]
        assert driver.robot_name == "phalanx-emu"
        assert driver.subtype == "p3dx-sh"
        limits = driver.robot_limits()
        assert limits == pytest.approx((ROBOT.v_max_mps, math.radians(ROBOT.omega_max_degps)))
        assert pty_emulator.stats.commands["ENABLE"] == 1
        status = driver.read_status()
        assert status.battery_v == pytest.approx(12.5)
        assert len(status.sonar_ranges_m) == 16


def test_a_sip_is_stamped_when_it_was_sent_not_when_its_last_byte_came() -> None:
    # A SIP with the sonar ring is about 80 bytes: most of a 100 ms cycle at 9600 baud.
    assert 80 * byte_time_s("/dev/ttyUSB0", 9600) == pytest.approx(0.0833, abs=1e-4)
    assert 80 * byte_time_s("/dev/ttyUSB0", 115200) == pytest.approx(0.0069, abs=1e-4)
    link = PtyLink()
    try:
        assert byte_time_s(link.device, 9600) == 0.0  # an emulator: no time on the wire
    finally:
        link.close()


def test_odometry_crosses_the_counter_wrap_without_a_jump() -> None:
    # p3dx (not -sh): 0.485 mm per count, so the 15-bit counter wraps every 15.9 m.
    wrap_m = 0x8000 * 0.485 / 1000
    body = Body(ROBOT, start=Pose2D(wrap_m - 0.1, 0.0, 0.0))
    options = EmulatorOptions(subtype="p3dx")
    with (
        ArcosEmulator(TcpLink(0), ROBOT, options, body) as emulator,
        ArcosDriver(_tcp(emulator), robot=ROBOT) as driver,
    ):
        deadline = time.monotonic() + 3.0
        while body.state().pose.x_m < wrap_m + 0.15 and time.monotonic() < deadline:
            driver.set_velocity(Twist2D(0.3, 0.0))
            time.sleep(0.1)
        driver.stop()
        time.sleep(0.3)
        travelled = body.state().pose.x_m - (wrap_m - 0.1)
        assert travelled > 0.25
        assert driver.read_odometry().pose.x_m == pytest.approx(travelled, abs=0.05)


def test_garbled_bytes_and_dropped_sips_are_survived_and_counted(
    tcp_emulator: ArcosEmulator,
) -> None:
    with ArcosDriver(_tcp(tcp_emulator), robot=ROBOT) as driver:
        sips = driver.stats.sips
        tcp_emulator.garble(200)
        tcp_emulator.drop_sips(5)  # 0.5 s: under the 1 s link timeout
        assert wait_for(lambda: driver.stats.sips > sips + 5, 3.0, poll_s=0.02)
        assert driver.parser.stats.bad_checksums + driver.parser.stats.garbage_bytes > 0
        assert driver.link_up
        assert driver.stats.links_lost == 0


def test_silent_robot_is_declared_lost_then_reconnected(tcp_emulator: ArcosEmulator) -> None:
    with ArcosDriver(_tcp(tcp_emulator, link_timeout_s=0.5), robot=ROBOT) as driver:
        tcp_emulator.drop_sips(15)  # 1.5 s of silence
        assert wait_for(lambda: not driver.link_up, 2.0, poll_s=0.02)
        assert "link lost" in driver.read_status().faults[0]
        with pytest.raises(Exception, match="link"):
            driver.set_velocity(Twist2D(0.1, 0.0))
        assert wait_for(lambda: driver.link_up, 5.0, poll_s=0.02)
        assert driver.stats.reconnects == 1
        driver.set_velocity(Twist2D(0.1, 0.0))


def test_tcp_disconnect_is_noticed_and_the_driver_reconnects(tcp_emulator: ArcosEmulator) -> None:
    with ArcosDriver(_tcp(tcp_emulator), robot=ROBOT) as driver:
        tcp_emulator.disconnect()
        assert wait_for(lambda: not driver.link_up, 2.0, poll_s=0.02)
        assert wait_for(lambda: driver.link_up, 5.0, poll_s=0.02)
        assert driver.stats.links_lost == 1


def test_unplugged_serial_port_reports_the_fault_and_stays_stopped(
    pty_emulator: ArcosEmulator,
) -> None:
    settings_ = ArcosSettings(port=pty_emulator.link.device)  # type: ignore[attr-defined]
    with ArcosDriver(settings_, robot=ROBOT) as driver:
        driver.set_velocity(Twist2D(0.2, 0.0))
        pty_emulator.disconnect()  # the device disappears
        assert wait_for(lambda: not driver.link_up, 2.0, poll_s=0.02)
        status = driver.read_status()
        assert not status.motors_enabled
        assert status.faults
        # Nothing moves a robot whose link is gone: commands are refused, not queued.
        with pytest.raises(Exception, match="link"):
            driver.set_velocity(Twist2D(0.2, 0.0))


def test_estop_button_and_stall_show_in_the_status(tcp_emulator: ArcosEmulator) -> None:
    with ArcosDriver(_tcp(tcp_emulator), robot=ROBOT) as driver:
        tcp_emulator.press_estop()
        tcp_emulator.stall()
        assert wait_for(lambda: driver.read_status().estopped, 1.0, poll_s=0.02)
        assert wait_for(lambda: driver.read_status().stalled, 1.0, poll_s=0.02)
        assert not driver.read_status().motors_enabled


def test_firmware_watchdog_stops_and_resumes() -> None:
    options = EmulatorOptions(watchdog_s=0.3)
    with (
        ArcosEmulator(TcpLink(0), ROBOT, options) as emulator,
        ArcosDriver(_tcp(emulator, link_timeout_s=5.0), robot=ROBOT) as driver,
    ):
        driver.set_velocity(Twist2D(0.2, 0.0))
        assert wait_for(lambda: emulator.body.state().twist.v_mps > 0.1, 2.0, poll_s=0.02)
        time.sleep(0.5)  # the driver keeps the robot's 0.3 s watchdog fed (PULSE at 1/4)
        assert emulator.stats.watchdog_stops == 0
        emulator.unplug()  # silence: the firmware stops the motors on its own
        assert wait_for(lambda: emulator.stats.watchdog_stops == 1, 2.0, poll_s=0.02)
        assert wait_for(lambda: emulator.body.state().twist.v_mps == 0.0, 2.0, poll_s=0.02)
        emulator.unplug(False)  # packets again: the last setpoints resume (ARCOS)
        assert wait_for(lambda: emulator.body.state().twist.v_mps > 0.1, 2.0, poll_s=0.02)
        driver.stop()
        assert wait_for(
            lambda: emulator.body.state().setpoint == Twist2D(0.0, 0.0), 1.0, poll_s=0.02
        )


def test_fuzzed_sip_stream_never_crashes_nor_commands_beyond_limits(
    pty_emulator: ArcosEmulator,
) -> None:
    """Random bytes and corrupted SIPs from the robot while a controller commands from
    whatever odometry it reads: the driver keeps running and every command the robot
    receives is within the limits."""
    rng = random.Random(7)
    limits = SafetyLimits(v_max_mps=0.3, omega_max_radps=math.radians(40.0))
    device = pty_emulator.link.device  # type: ignore[attr-defined]
    seen: list[Twist2D] = []
    with SafeDriver(
        ArcosDriver(ArcosSettings(port=device, link_timeout_s=5.0), robot=ROBOT), limits
    ) as safe:
        for _ in range(60):
            junk = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64)))
            if rng.random() < 0.3:
                junk = b"\xfa\xfb" + bytes((rng.randrange(256),)) + junk
            pty_emulator.link.write(junk)
            odo = safe.read_odometry()
            # A "controller" driven by the readings: gains large enough to ask for too much.
            wanted = Twist2D(10.0 * odo.twist.v_mps + 5.0, -20.0 * odo.pose.theta_rad - 3.0)
            safe.set_velocity(wanted)
            seen.append(pty_emulator.body.state().setpoint)
            time.sleep(0.01)
        stats = safe.driver.parser.stats  # type: ignore[attr-defined]
        assert stats.garbage_bytes + stats.bad_checksums + stats.bad_lengths > 0
    assert seen
    for setpoint in seen:
        assert abs(setpoint.v_mps) <= limits.v_max_mps + 1e-3
        assert abs(setpoint.omega_radps) <= math.radians(41.0)


def test_a_pty_without_robot_fails_to_connect_with_a_clear_error() -> None:
    link = PtyLink()
    try:
        settings_ = ArcosSettings(port=link.device, connect_timeout_s=0.3, sync_retries=1)
        with pytest.raises(Exception, match="no ARCOS sync"):
            ArcosDriver(settings_, robot=ROBOT).connect()
    finally:
        link.close()
    assert not os.path.exists(link.device) or True  # the pty is released either way


def test_settings_reject_ambiguous_links() -> None:
    with pytest.raises(ValueError, match="exactly one"):
        ArcosSettings()
    with pytest.raises(ValueError, match="host:port"):
        ArcosSettings(tcp="localhost")


# -- what the driver makes of the robot's CONFIG packet, E-stops and addresses --------


def test_the_driver_reads_every_config_field_the_emulator_writes(
    tcp_emulator: ArcosEmulator,
) -> None:
    with ArcosDriver(_tcp(tcp_emulator), robot=ROBOT) as driver:
        written = tcp_emulator.config()
        read = driver.robot_config
        assert read is not None
        for name in ("trans_vel_max_mmps", "rot_vel_max_degps", "watchdog_ms", "serial", "name"):
            assert getattr(read, name) == getattr(written, name), name
        assert read == written  # every field, in order
        assert read.fields_read == len(FIELDS)


def test_the_keepalive_follows_the_robots_watchdog() -> None:
    # A robot whose watchdog is 0.3 s: PULSE at most every 75 ms, so it never trips.
    options = EmulatorOptions(watchdog_s=0.3)
    with (
        ArcosEmulator(TcpLink(0), ROBOT, options) as emulator,
        ArcosDriver(_tcp(emulator), robot=ROBOT) as driver,
    ):
        driver.set_velocity(Twist2D(0.2, 0.0))
        time.sleep(1.5)
        assert emulator.stats.watchdog_stops == 0
        assert emulator.body.state().setpoint.v_mps > 0.1


def test_a_robot_that_brakes_softer_than_the_robot_file_is_told_to_brake_harder() -> None:
    soft = ROBOT.model_copy(update={"decel_mps2": 0.1, "rot_accel_degps2": 50.0})
    with (
        ArcosEmulator(TcpLink(0), soft) as emulator,
        ArcosDriver(_tcp(emulator), robot=ROBOT) as driver,
    ):
        assert driver.robot_config is not None
        assert driver.robot_config.trans_decel_mmps2 == 100
        # (two commands, taken one after the other: wait for each)
        assert wait_for(lambda: emulator.limits.trans_decel == 300.0, 1.0, poll_s=0.02)
        assert wait_for(lambda: emulator.limits.rot_decel == 100.0, 1.0, poll_s=0.02)
        assert emulator.limits.trans_accel == 300.0  # already the robot file's: untouched


def test_an_estop_holds_in_the_driver_though_the_firmware_lets_go(
    tcp_emulator: ArcosEmulator,
) -> None:
    with ArcosDriver(_tcp(tcp_emulator), robot=ROBOT) as driver:
        driver.set_velocity(Twist2D(0.3, 0.0))
        assert wait_for(lambda: tcp_emulator.body.state().twist.v_mps > 0.2, 3.0, poll_s=0.02)
        driver.estop()
        assert wait_for(lambda: tcp_emulator.body.state().twist.v_mps == 0.0, 1.0, poll_s=0.02)
        vels = tcp_emulator.stats.commands.get("VEL", 0)
        assert driver.read_status().estopped
        assert not driver.read_status().motors_enabled
        with pytest.raises(Exception, match="E-stopped"):
            driver.set_velocity(Twist2D(0.3, 0.0))
        driver.set_velocity(Twist2D(0.0, 0.0))  # a zero command: accepted, nothing sent
        time.sleep(0.3)
        assert tcp_emulator.stats.commands.get("VEL", 0) == vels  # nothing reached it
        assert tcp_emulator.body.state().twist.v_mps == 0.0
        driver.connect()  # the deliberate reset
        assert not driver.read_status().estopped
        driver.set_velocity(Twist2D(0.2, 0.0))
        assert wait_for(lambda: tcp_emulator.body.state().twist.v_mps > 0.1, 3.0, poll_s=0.02)


def test_the_robots_estop_button_latches_until_released_and_reset(
    tcp_emulator: ArcosEmulator,
) -> None:
    with ArcosDriver(_tcp(tcp_emulator), robot=ROBOT) as driver:
        tcp_emulator.press_estop()
        assert wait_for(lambda: driver.read_status().estopped, 1.0, poll_s=0.02)
        with pytest.raises(Exception, match="still pressed"):
            driver.connect()
        tcp_emulator.press_estop(False)
        time.sleep(0.3)
        assert driver.read_status().estopped  # released, but nobody reset it
        driver.connect()
        assert wait_for(lambda: driver.read_status().motors_enabled, 1.0, poll_s=0.02)
        assert not driver.read_status().estopped


def test_a_lost_robot_is_found_again_at_a_fallback_address() -> None:
    with (
        ArcosEmulator(TcpLink(0), ROBOT) as first,
        ArcosEmulator(TcpLink(0), ROBOT) as second,  # the same robot, as its serial says
    ):
        settings = _tcp(first, fallbacks=(f"127.0.0.1:{second.link.port}",))  # type: ignore[attr-defined]
        with ArcosDriver(settings, robot=ROBOT) as driver:
            first.close()
            assert wait_for(lambda: not driver.link_up, 2.0, poll_s=0.02)
            assert wait_for(lambda: driver.link_up, 8.0, poll_s=0.02)
            assert driver.address == f"127.0.0.1:{second.link.port}"  # type: ignore[attr-defined]


def test_another_robot_at_a_fallback_address_is_not_taken_for_this_one() -> None:
    other = EmulatorOptions(name="other-robot", serial="OTHER-0002")
    with (
        ArcosEmulator(TcpLink(0), ROBOT) as first,
        ArcosEmulator(TcpLink(0), ROBOT, other) as second,
    ):
        settings = _tcp(
            first,
            fallbacks=(f"127.0.0.1:{second.link.port}",),
            connect_timeout_s=0.5,  # type: ignore[attr-defined]
        )
        with ArcosDriver(settings, robot=ROBOT) as driver:
            first.close()
            assert wait_for(
                lambda: "another robot" in str(driver.read_status().faults), 5.0, poll_s=0.02
            )
            assert not driver.link_up


def test_fallbacks_must_be_serial_devices_or_host_ports() -> None:
    with pytest.raises(ValueError, match="fallback"):
        ArcosSettings(port="/dev/ttyUSB0", fallbacks=("ttyUSB1",))
    assert ArcosSettings(port="/dev/ttyUSB0", fallbacks=("/dev/ttyUSB1", "lab:8102")).addresses == (
        ("/dev/ttyUSB0", False), ("/dev/ttyUSB1", False), ("lab:8102", True),
    )  # fmt: skip
