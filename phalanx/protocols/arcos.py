"""ARCOS wire protocol, both sides: framing, checksums, commands and SIPs.

Pure functions and a byte-stream parser, no I/O: the `arcos` driver (client side) and
the robot emulator (`phalanx.simulator.arcos_emulator`, robot side) share it; the CONFIG
packet is `phalanx.protocols.arcos_config`. Facts from AriaCoda `src/ArRobotPacket.cpp`
and `src/ArRobotPacketSender.cpp` (framing, checksum, integer arguments),
`include/Aria/ArCommands.h` (command numbers), `src/ArRobot.cpp` (SIP layout, odometry
wrap-around), AMRISim's `EmulatePioneer.cc` (the robot side) and the Pioneer 3 operations
manual; docs/HARDWARE.md has the facts and the test vectors the tests pin.

A frame: `FA FB | N | cmd | args... | chk_hi chk_lo`, N = bytes from cmd through the
checksum. Ints are 16-bit little-endian, preceded by 0x3B (>= 0) or 0x1B (< 0, magnitude
follows); strings by 0x2B and a length byte.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from enum import IntEnum

from phalanx.core.errors import ProtocolError
from phalanx.protocols.arcos_config import CONFIG_PAC, RobotConfig, decode_config, encode_config

HEADER = b"\xfa\xfb"
MAX_LENGTH = 204  # ARCOS ignores a length byte above this (ArRobotPacket)
ARG_INT_POS = 0x3B
ARG_INT_NEG = 0x1B
ARG_STR = 0x2B
INT_MAX = 0x7FFF  # magnitude limit of an ARCOS integer argument


class Cmd(IntEnum):
    """Client command numbers (ArCommands.h)."""

    PULSE = 0
    OPEN = 1
    CLOSE = 2
    ENABLE = 4
    SETA = 5
    SETV = 6
    SETO = 7
    MOVE = 8
    ROTATE = 9
    SETRV = 10
    VEL = 11
    HEAD = 12
    DHEAD = 13
    CONFIG = 18
    ENCODER = 19
    RVEL = 21
    SETRA = 23
    SONAR = 28
    STOP = 29
    VEL2 = 32
    BUMPSTALL = 44
    E_STOP = 55
    # Simulators' own commands (MobileSim, AMRISim; ArCommands.h): a firmware ignores them.
    SIM_SET_POSE = 224
    SIM_STAT = 237


SYNC0, SYNC1, SYNC2 = 0, 1, 2
SIP_STOPPED, SIP_MOVING = 0x32, 0x33
SIMSTAT = 0x62  # a simulator's report on itself and the robot's true pose
SIMSTAT_CONTINUOUS = 2  # SIM_STAT's argument: a SIMSTAT before every SIP (0 stops, 1 once)
__all__ = ["CONFIG_PAC", "RobotConfig", "decode_config", "encode_config"]  # re-exported


def checksum(body: bytes) -> int:
    """ARCOS checksum of `cmd..end of data`: big-endian 16-bit sum, odd last byte XORed."""
    c = 0
    n = len(body)
    for i in range(0, n - 1, 2):
        c = (c + (body[i] << 8 | body[i + 1])) & 0xFFFF
    if n % 2:
        c ^= body[-1]
    return c


def frame(body: bytes) -> bytes:
    """Wrap `body` (command/type byte and data) into a complete frame."""
    if len(body) + 2 > MAX_LENGTH:
        raise ProtocolError(f"ARCOS frame too long: {len(body) + 2} > {MAX_LENGTH}")
    c = checksum(body)
    return HEADER + bytes((len(body) + 2,)) + body + bytes((c >> 8, c & 0xFF))


def command(cmd: int, arg: int | str | None = None) -> bytes:
    """A client command frame with an optional int (clamped to +-32767) or string arg."""
    body = bytearray((cmd,))
    if isinstance(arg, str):
        raw = arg.encode("ascii")
        body += bytes((ARG_STR, len(raw))) + raw
    elif arg is not None:
        magnitude = min(abs(int(arg)), INT_MAX)
        body += bytes((ARG_INT_POS if arg >= 0 else ARG_INT_NEG,)) + struct.pack("<H", magnitude)
    return frame(bytes(body))


def int_arg(body: bytes) -> int | None:
    """The signed int argument of a command body (`cmd, type, lo, hi`), or None."""
    if len(body) < 4 or body[1] not in (ARG_INT_POS, ARG_INT_NEG):
        return None
    magnitude = int(struct.unpack_from("<H", body, 2)[0])
    return magnitude if body[1] == ARG_INT_POS else -magnitude


def vel2_arg(left: int, right: int) -> int:
    """VEL2's argument for wheel speeds in Vel2Divisor units (each clamped to a signed
    byte): the left wheel in the high byte, the right in the low byte, and the 16 bits
    read as one signed value, as ARIA's `com2Bytes` builds it (`setVel2(-200, -200)` on a
    P3DX: -10, -10 -> 0xF6F6 -> -2314, sent as 0x1B and magnitude 2314).
    """
    lo, hi = (max(-128, min(127, w)) & 0xFF for w in (right, left))
    raw = hi << 8 | lo
    return raw - 0x10000 if raw & 0x8000 else raw


def vel2_wheels(arg: int) -> tuple[int, int]:
    """(left, right) in Vel2Divisor units from VEL2's signed argument: the two bytes of
    its two's-complement value, each a signed byte (never the magnitude's bytes).
    """
    raw = arg & 0xFFFF
    return _signed_byte(raw >> 8), _signed_byte(raw & 0xFF)


def _signed_byte(value: int) -> int:
    return value - 0x100 if value & 0x80 else value


@dataclass
class ParserStats:
    """What a FrameParser skipped: bytes outside frames, bad checksums, bad lengths."""

    frames: int = 0
    garbage_bytes: int = 0
    bad_checksums: int = 0
    bad_lengths: int = 0

    @property
    def errors(self) -> int:
        """Frames dropped (bad checksum or length); garbage bytes are counted apart."""
        return self.bad_checksums + self.bad_lengths


@dataclass
class FrameParser:
    """Turns a byte stream into frame bodies; skips and counts anything that is not one.

    Resynchronises on the next `FA FB` after garbage, a bad checksum or a length out of
    range; a truncated frame waits for more bytes (and is dropped when the next header
    turns out to start inside it, by the checksum).
    """

    stats: ParserStats = field(default_factory=ParserStats)
    _buffer: bytearray = field(default_factory=bytearray)
    max_buffer: int = 4096

    def feed(self, data: bytes) -> Iterator[bytes]:
        """Add bytes; yield every complete, valid frame body (`cmd/type .. data`)."""
        buf = self._buffer
        buf += data
        while True:
            start = buf.find(HEADER)
            if start < 0:
                keep = 1 if buf.endswith(HEADER[:1]) else 0
                self.stats.garbage_bytes += len(buf) - keep
                del buf[: len(buf) - keep]
                return
            if start:
                self.stats.garbage_bytes += start
                del buf[:start]
            if len(buf) < 3:
                return
            n = buf[2]
            if n < 3 or n > MAX_LENGTH:  # at least a type byte and the checksum
                self.stats.bad_lengths += 1
                del buf[:2]
                continue
            if len(buf) < 3 + n:
                if len(buf) > self.max_buffer:
                    del buf[:2]
                return
            body = bytes(buf[3 : 3 + n - 2])
            got = buf[3 + n - 2] << 8 | buf[3 + n - 1]
            if got != checksum(body):
                self.stats.bad_checksums += 1
                del buf[:2]  # resync: the next header may start inside this "frame"
                continue
            del buf[: 3 + n]
            self.stats.frames += 1
            yield body


@dataclass(frozen=True)
class Sip:
    """A standard server information packet, in raw ARCOS units.

    x/y are the 15-bit wrapped encoder-derived counters; th in AngleConvFactor units;
    velocities in mm/s (VelConvFactor 1); battery in decivolts; sonar ranges in mm.
    """

    moving: bool
    x: int
    y: int
    th: int
    left_vel: int
    right_vel: int
    battery_dv: int
    stall_bumpers: int
    control: int = 0
    flags: int = 0
    compass: int = 0
    sonars: tuple[tuple[int, int], ...] = ()  # (index, range) of the sonars updated
    # The optional tail (ArRobot::processMotorPacket reads each field only if bytes remain):
    # the battery again, in decivolts over two bytes (ARIA's "real" battery voltage), the
    # yaw rate (deg/s x 10) and the fault flags. Encoded when rot_vel_x10 is set.
    rot_vel_x10: int | None = None
    battery_tail_dv: int | None = None
    fault_flags: int | None = None

    @property
    def battery_v(self) -> float | None:
        """Battery volts: the tail's two-byte value if sent, else the byte; None when both
        are 0 (firmware that reports state of charge instead of volts, battery type 2).
        """
        dv = self.battery_tail_dv or self.battery_dv
        return dv / 10.0 if dv else None

    @property
    def motors_enabled(self) -> bool:
        """Flags bit 0."""
        return bool(self.flags & 0x0001)

    @property
    def estopped(self) -> bool:
        """Flags bit 5 (the e-stop button, or an E_STOP command)."""
        return bool(self.flags & 0x0020)

    @property
    def left_stall(self) -> bool:
        """Stall/bumper bit 0."""
        return bool(self.stall_bumpers & 0x0001)

    @property
    def right_stall(self) -> bool:
        """Stall/bumper bit 8."""
        return bool(self.stall_bumpers & 0x0100)

    @property
    def bumpers(self) -> tuple[bool, ...]:
        """Front bumpers (bits 9-15) then rear bumpers (bits 1-7)."""
        front = tuple(bool(self.stall_bumpers >> (9 + i) & 1) for i in range(7))
        rear = tuple(bool(self.stall_bumpers >> (1 + i) & 1) for i in range(7))
        return front + rear


_SIP_HEAD = struct.Struct(
    "<HHhhhBHhHbB"
)  # x y th lvel rvel battery stallbump control flags compass nsonar


def encode_sip(sip: Sip) -> bytes:
    """The frame of `sip` (robot side)."""
    body = bytearray((SIP_MOVING if sip.moving else SIP_STOPPED,))
    body += _SIP_HEAD.pack(
        sip.x & 0x7FFF,
        sip.y & 0x7FFF,
        sip.th,
        sip.left_vel,
        sip.right_vel,
        sip.battery_dv,
        sip.stall_bumpers,
        sip.control,
        sip.flags,
        sip.compass,
        len(sip.sonars),
    )
    for index, range_mm in sip.sonars:
        body += struct.pack("<BH", index, min(range_mm, 0xFFFF))
    if sip.rot_vel_x10 is not None:
        # anport (2), analog, digin, digout; battery (decivolts, 2 bytes), charge state, rotvel
        battery = sip.battery_dv if sip.battery_tail_dv is None else sip.battery_tail_dv
        body += bytes(5) + struct.pack("<HBh", battery, 0, sip.rot_vel_x10)
        if sip.fault_flags is not None:
            body += struct.pack("<H", sip.fault_flags)
    return frame(bytes(body))


def decode_sip(body: bytes) -> Sip:
    """Parse a SIP frame body (type byte first); ProtocolError if it is not one."""
    if not body or body[0] not in (SIP_STOPPED, SIP_MOVING):
        raise ProtocolError(f"not a standard SIP: type {body[:1].hex()}")
    if len(body) < 1 + _SIP_HEAD.size:
        raise ProtocolError(f"SIP too short: {len(body)} bytes")
    x, y, th, lvel, rvel, batt, stall, control, flags, compass, nsonar = _SIP_HEAD.unpack_from(
        body, 1
    )
    offset = 1 + _SIP_HEAD.size
    if len(body) < offset + 3 * nsonar:
        raise ProtocolError(f"SIP announces {nsonar} sonars, has room for fewer")
    sonars = tuple(struct.unpack_from("<BH", body, offset + 3 * i) for i in range(nsonar))
    offset += 3 * nsonar
    rot_vel = battery_tail = faults = None
    if len(body) >= offset + 10:
        battery_tail, _charge, rot_vel = struct.unpack_from("<HBh", body, offset + 5)
    if len(body) >= offset + 12:
        (faults,) = struct.unpack_from("<H", body, offset + 10)
    return Sip(
        moving=body[0] == SIP_MOVING,
        x=x & 0x7FFF,
        y=y & 0x7FFF,
        th=th,
        left_vel=lvel,
        right_vel=rvel,
        battery_dv=batt,
        stall_bumpers=stall,
        control=control,
        flags=flags,
        compass=compass,
        sonars=sonars,
        rot_vel_x10=rot_vel,
        battery_tail_dv=battery_tail,
        fault_flags=faults,
    )


def sim_set_pose(x_mm: int, y_mm: int, th_deg: int) -> bytes:
    """SIM_SET_POSE: move a simulated robot to a true pose (the simulator's frame; its
    odometry is left as it is). An unused byte, then three 4-byte little-endian integers,
    as ARIA's `ArSimUtil::setSimTruePose` sends it.
    """
    body = bytes((Cmd.SIM_SET_POSE, 0)) + struct.pack("<iii", x_mm, y_mm, th_deg)
    return frame(body)


@dataclass(frozen=True)
class SimStat:
    """A simulator's SIMSTAT packet: its loop's timing and the robot's true pose (mm and
    whole degrees: AMRISim rounds the heading, and truncates x and y to the millimetre).
    """

    flags: int
    sim_interval_ms: int  # simulated time one update takes
    real_interval_ms: int  # the real time it should take
    last_interval_ms: int  # the real time the last one took
    x_mm: int
    y_mm: int
    th_deg: int


_SIMSTAT_HEAD = struct.Struct("<xxIHHHiiii")  # two NULs, flags, 3 intervals, x y z th


def encode_simstat(stat: SimStat) -> bytes:
    """The frame of `stat` (simulator side), with AMRISim's tail of no GPS, no odometry
    error: latitude, longitude, altitude 0, GPS -1, odometry errors 0.
    """
    body = bytes((SIMSTAT,)) + _SIMSTAT_HEAD.pack(
        stat.flags, stat.sim_interval_ms, stat.real_interval_ms, stat.last_interval_ms,
        stat.x_mm, stat.y_mm, 0, stat.th_deg,
    )  # fmt: skip
    return frame(body + struct.pack("<iiiiiii", 0, 0, 0, -1, 0, 0, 0))


def decode_simstat(body: bytes) -> SimStat:
    """Parse a SIMSTAT body (type byte first) as far as the true pose (AMRISim's
    `EmulatePioneer::sendSIMSTAT`; later fields vary between versions); ProtocolError if
    it is not one or ends before the pose.
    """
    if not body or body[0] != SIMSTAT:
        raise ProtocolError(f"not a SIMSTAT packet: type {body[:1].hex() or 'none'}")
    if len(body) < 1 + _SIMSTAT_HEAD.size:
        raise ProtocolError(f"SIMSTAT too short: {len(body)} bytes")
    flags, sim_ms, real_ms, last_ms, x, y, _z, th = _SIMSTAT_HEAD.unpack_from(body, 1)
    return SimStat(flags, sim_ms, real_ms, last_ms, x, y, th)


def wrap_delta(now: int, last: int) -> int:
    """Difference of two 15-bit position counters across their wrap-around (ArRobot)."""
    d = now - last
    if d > 0x1000:
        d -= 0x8000
    elif d < -0x1000:
        d += 0x8000
    return d


def sync2_reply(name: str, robot_type: str, subtype: str) -> bytes:
    """The robot's answer to SYNC2: three NUL-terminated strings."""
    body = bytes((SYNC2,)) + b"".join(
        s.encode("ascii") + b"\0" for s in (name, robot_type, subtype)
    )
    return frame(body)


def parse_sync2(body: bytes) -> tuple[str, str, str]:
    """(name, type, subtype) from the SYNC2 reply body."""
    parts = body[1:].split(b"\0")
    if len(parts) < 3:
        raise ProtocolError(f"SYNC2 reply without name/type/subtype: {body!r}")
    name, robot_type, subtype = (p.decode("ascii", "replace") for p in parts[:3])
    return name, robot_type, subtype


@dataclass(frozen=True)
class ConvFactors:
    """Unit conversions of a robot subtype (AriaCoda params/p3dx*.p)."""

    dist_mm: float = 1.0  # DistConvFactor: mm per position count
    angle_rad: float = 2 * math.pi / 4096  # AngleConvFactor
    vel_mmps: float = 1.0  # VelConvFactor
    range_mm: float = 1.0  # RangeConvFactor
    diff: float = 0.0056  # DiffConvFactor: (rvel - lvel) / 2 * diff = rad/s


SUBTYPES = {"p3dx-sh": ConvFactors(dist_mm=1.0), "p3dx": ConvFactors(dist_mm=0.485)}


def factors_for(subtype: str) -> ConvFactors:
    """Conversion factors of `subtype` (p3dx-sh when unknown, as ARIA's default)."""
    return SUBTYPES.get(subtype.lower(), SUBTYPES["p3dx-sh"])
