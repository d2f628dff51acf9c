"""ARCOS bytes, written from the protocol (AriaCoda's ArRobotPacketSender and
ArRobotConfigPacketReader, AMRISim's EmulatePioneer, the Pioneer 3 manual): every motion
command byte for byte, VEL2's signed wheels, the whole CONFIG packet in ARIA's field order
(and the shorter packets of older firmware), the SIP's battery in volts."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from phalanx.core.errors import ProtocolError
from phalanx.protocols.arcos import (
    Cmd,
    FrameParser,
    SimStat,
    Sip,
    command,
    decode_simstat,
    decode_sip,
    encode_simstat,
    encode_sip,
    sim_set_pose,
    vel2_arg,
    vel2_wheels,
)
from phalanx.protocols.arcos_config import FIELDS, RobotConfig, decode_config, encode_config

pytestmark = pytest.mark.drivers

# Every command an ARIA program sends to move a P3DX, byte for byte (checksums worked by
# hand: the big-endian 16-bit sum of the body, e.g. VEL2: 0x201B + 0x0A09 = 0x2A24).
VECTORS = [
    (Cmd.SETA, 300, "FA FB 06 05 3B 2C 01 31 3C"),
    (Cmd.SETA, -300, "FA FB 06 05 1B 2C 01 31 1C"),  # negative: the deceleration
    (Cmd.SETV, 1200, "FA FB 06 06 3B B0 04 B6 3F"),
    (Cmd.SETO, None, "FA FB 03 07 00 07"),
    (Cmd.MOVE, 1000, "FA FB 06 08 3B E8 03 F0 3E"),
    (Cmd.MOVE, -500, "FA FB 06 08 1B F4 01 FC 1C"),
    (Cmd.ROTATE, 10, "FA FB 06 09 3B 0A 00 13 3B"),
    (Cmd.SETRV, 300, "FA FB 06 0A 3B 2C 01 36 3C"),
    (Cmd.HEAD, 90, "FA FB 06 0C 3B 5A 00 66 3B"),
    (Cmd.HEAD, -90, "FA FB 06 0C 1B 5A 00 66 1B"),
    (Cmd.DHEAD, -45, "FA FB 06 0D 1B 2D 00 3A 1B"),
    (Cmd.CONFIG, None, "FA FB 03 12 00 12"),
    (Cmd.RVEL, 10, "FA FB 06 15 3B 0A 00 1F 3B"),
    (Cmd.SETRA, 100, "FA FB 06 17 3B 64 00 7B 3B"),
    (Cmd.SETRA, -100, "FA FB 06 17 1B 64 00 7B 1B"),
    (Cmd.SONAR, 1, "FA FB 06 1C 3B 01 00 1D 3B"),
    (Cmd.VEL2, -2314, "FA FB 06 20 1B 0A 09 2A 24"),  # ARIA's setVel2(-200, -200)
    (Cmd.BUMPSTALL, 0, "FA FB 06 2C 3B 00 00 2C 3B"),
]


@pytest.mark.parametrize(("cmd", "arg", "expected"), VECTORS)
def test_every_motion_command_is_byte_exact(cmd: Cmd, arg: int | None, expected: str) -> None:
    assert command(cmd, arg) == bytes.fromhex(expected)
    assert list(FrameParser().feed(bytes.fromhex(expected))) == [bytes.fromhex(expected)[3:-2]]


def test_vel2_is_the_two_bytes_of_a_signed_value_not_of_its_magnitude() -> None:
    # setVel2(-200, -200) on a P3DX (Vel2Divisor 20): -10 and -10 -> 0xF6F6 -> -2314.
    assert vel2_arg(-10, -10) == -2314
    assert vel2_wheels(-2314) == (-10, -10)
    # Reading the magnitude's bytes (0x090A) instead gives +9 and +10: forwards.
    assert vel2_wheels(2314) == (9, 10)
    assert vel2_wheels(vel2_arg(-5, 5)) == (-5, 5)  # a turn on the spot, left wheel back


@given(st.integers(-128, 127), st.integers(-128, 127))
def test_vel2_round_trips_every_wheel_pair(left: int, right: int) -> None:
    assert vel2_wheels(vel2_arg(left, right)) == (left, right)


def _amrisim_config(*, joy_rot_vel: int = 0) -> bytes:
    """A CONFIG body as AMRISim's P3DX sends it, built field by field in ARIA's order."""
    u1, u2 = (lambda v: struct.pack("<B", v)), (lambda v: struct.pack("<H", v))
    body = b"\x20" + b"Pioneer\0p3dx\0SIM\0" + u1(0)
    body += u2(9999) + u2(9999) + u2(9999) + u2(9999) + u2(400) + b"AMRISim\0"
    body += u1(100) + u1(0) + u1(0) + u2(0) + u2(1) + u1(1)  # .. FrontSonar (2), RearSonar (1)
    body += u2(0) + u2(0) + u2(2000) + u1(0) + u2(0) + u2(0)  # lowbat revcount watchdog ..
    body += u2(0) + u2(joy_rot_vel) + u2(150) + u2(3000)  # joyvel joyrvel rotvelmax transvelmax
    body += u2(100) + u2(100) + u2(0) * 3 + u2(300) + u2(300) + u2(0) * 3  # accels, PIDs
    body += u1(0) * 4 + u1(2) + u1(0) + u2(0) + u1(0) + u1(0) + u2(0) + u2(0)
    body += b"S.0\0" + u2(0) + u2(0) + u1(0) + u2(9999) + u2(9999) + u2(0) * 4
    return body


def test_the_config_packet_is_read_in_arias_field_order() -> None:
    config = decode_config(_amrisim_config())
    assert (config.robot_type, config.subtype, config.serial, config.name) == (
        "Pioneer", "p3dx", "SIM", "AMRISim",
    )  # fmt: skip
    assert config.front_sonar == 1  # two bytes; RearSonar one
    assert config.watchdog_ms == 2000  # read one byte early, this was 7 ms
    assert config.trans_vel_max_mmps == 3000  # ... and this 0
    assert config.rot_vel_max_degps == 150
    assert (config.trans_accel_mmps2, config.trans_decel_mmps2) == (300, 300)
    assert (config.rot_accel_degps2, config.rot_decel_degps2) == (100, 100)
    assert config.reset_baud == 2
    assert config.firmware_version == "S.0"
    assert config.lat_vel_top_mmps == 9999
    assert config.fields_read == 57  # AMRISim stops after the charge threshold


def test_a_robot_whose_joystick_turns_at_50_is_not_capped_at_50_mm_per_s() -> None:
    assert decode_config(_amrisim_config(joy_rot_vel=50)).trans_vel_max_mmps == 3000


def test_older_firmware_sends_shorter_packets_and_the_rest_stays_unknown() -> None:
    full = _amrisim_config()
    # After the name: SipCycle 1, HostBaud 1, Aux1Baud 1, HasGripper 2, FrontSonar 2,
    # RearSonar 1, LowBattery 2, RevCount 2, Watchdog 2: a packet that ends there.
    end = full.index(b"AMRISim\0") + len(b"AMRISim\0") + 14
    config = decode_config(full[:end])
    assert config.watchdog_ms == 2000
    assert config.has("watchdog_ms")
    assert not config.has("trans_vel_max_mmps")
    assert config.trans_vel_max_mmps == 0  # not sent: the driver reports no limits then


def test_a_config_packet_that_ends_in_its_first_strings_is_refused() -> None:
    with pytest.raises(ProtocolError, match="CONFIG"):
        decode_config(b"\x20Pioneer\0p3d")
    with pytest.raises(ProtocolError, match="not a CONFIG"):
        decode_config(b"\x32" + bytes(30))


def test_every_field_round_trips_in_order() -> None:
    values = {}
    for i, (name, kind) in enumerate(FIELDS):
        values[name] = f"f{i}" if kind == "str" else (-i if kind[0] == "s" else i)
    config = RobotConfig(**values)  # type: ignore[arg-type]
    got = decode_config(encode_config(config))
    assert got == config
    assert got.fields_read == len(FIELDS)


def test_encode_refuses_a_value_its_field_cannot_hold() -> None:
    with pytest.raises(ValueError, match="watchdog_ms=70000"):
        encode_config(RobotConfig(watchdog_ms=70000))


def test_the_sip_battery_is_in_decivolts_in_the_byte_and_in_the_tail() -> None:
    sip = Sip(
        moving=False, x=0, y=0, th=0, left_vel=0, right_vel=0, battery_dv=125,
        stall_bumpers=0, rot_vel_x10=0,
    )  # fmt: skip
    raw = encode_sip(sip)
    assert raw[14] == 125  # offset 14 from FA: the battery byte
    # The tail after the (empty) sonar list: anport 2, analog, digin, digout, then
    # the battery again as two bytes (ArRobot's getRealBatteryVoltage): 125, not 1250.
    assert struct.unpack_from("<H", raw, 23 + 5)[0] == 125
    decoded = decode_sip(raw[3:-2])
    assert decoded.battery_v == pytest.approx(12.5)


def test_a_sip_without_a_battery_voltage_reports_none() -> None:
    # Battery type 2 firmware reports a state of charge instead: 0 V is not a reading.
    sip = Sip(moving=False, x=0, y=0, th=0, left_vel=0, right_vel=0, battery_dv=0, stall_bumpers=0)
    assert decode_sip(encode_sip(sip)[3:-2]).battery_v is None


def test_sim_set_pose_is_an_unused_byte_and_three_four_byte_integers() -> None:
    """As ARIA's ArSimUtil::setSimTruePose writes it (and AMRISim reads it): the command,
    a byte AMRISim ignores, then x, y (mm) and heading (deg), 4 bytes each, little-endian."""
    frame = sim_set_pose(-1050, 1000, 12)
    body = frame[3:-2]
    assert frame[:3] == bytes((0xFA, 0xFB, len(body) + 2))
    assert body[:2] == bytes((Cmd.SIM_SET_POSE, 0))
    assert struct.unpack("<iii", body[2:]) == (-1050, 1000, 12)
    assert list(FrameParser().feed(frame)) == [body]


@given(
    x=st.integers(-(2**31), 2**31 - 1),
    y=st.integers(-(2**31), 2**31 - 1),
    th=st.integers(-180, 180),
    intervals=st.tuples(*(st.integers(0, 0xFFFF) for _ in range(3))),
)
def test_simstat_round_trips_as_far_as_the_true_pose(
    x: int, y: int, th: int, intervals: tuple[int, int, int]
) -> None:
    stat = SimStat(0b100, *intervals, x_mm=x, y_mm=y, th_deg=th)
    (body,) = FrameParser().feed(encode_simstat(stat))
    assert decode_simstat(body) == stat


def test_a_short_or_foreign_simstat_is_refused() -> None:
    (body,) = FrameParser().feed(encode_simstat(SimStat(0, 100, 100, 100, 1, 2, 3)))
    with pytest.raises(ProtocolError, match="too short"):
        decode_simstat(body[:20])
    with pytest.raises(ProtocolError, match="not a SIMSTAT"):
        decode_simstat(bytes((0x32,)) + body[1:])
