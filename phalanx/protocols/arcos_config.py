"""The ARCOS CONFIG packet (type 0x20, the robot's answer to CONFIG #18), both sides.

Every field in the order ARIA's reader takes them (AriaCoda
`src/ArRobotConfigPacketReader.cpp`; AMRISim's `EmulatePioneer.cc` writes the same order):
three NUL-terminated strings, a spare byte, the "top" limits, the robot's name, then the
firmware's working settings. Integers are little-endian; `u1`/`u2`/`u4` unsigned, `s1`/`s2`
signed. Older firmware sends shorter packets: the reader keeps what the packet holds and
leaves every later field at its default (0 or ""), and `RobotConfig.has(field)` says whether
a field came at all. docs/HARDWARE.md lists the fields with their units.
"""

from __future__ import annotations

import struct
from dataclasses import astuple, dataclass, field, fields

from phalanx.core.errors import ProtocolError

CONFIG_PAC = 0x20
_INT_FORMATS = {"u1": "<B", "s1": "<b", "u2": "<H", "s2": "<h", "u4": "<I"}


@dataclass(frozen=True)
class RobotConfig:
    """A CONFIG packet's fields, in ARCOS units (mm, deg, ms, decivolts), in packet order.

    `fields_read` is how many leading fields the packet carried (all of them when encoded
    by `encode_config`); the fields after those hold their defaults.
    """

    robot_type: str = "Pioneer"
    subtype: str = ""
    serial: str = ""
    four_mots: int = field(default=0, metadata={"kind": "u1"})
    rot_vel_top_degps: int = field(default=0, metadata={"kind": "u2"})
    trans_vel_top_mmps: int = field(default=0, metadata={"kind": "u2"})
    rot_accel_top_degps2: int = field(default=0, metadata={"kind": "u2"})
    trans_accel_top_mmps2: int = field(default=0, metadata={"kind": "u2"})
    pwm_max: int = field(default=0, metadata={"kind": "u2"})
    name: str = ""
    sip_cycle_ms: int = field(default=0, metadata={"kind": "u1"})
    host_baud: int = field(default=0, metadata={"kind": "u1"})
    aux1_baud: int = field(default=0, metadata={"kind": "u1"})
    has_gripper: int = field(default=0, metadata={"kind": "u2"})
    front_sonar: int = field(default=0, metadata={"kind": "u2"})  # 2 bytes, rear sonar 1
    rear_sonar: int = field(default=0, metadata={"kind": "u1"})
    low_battery_dv: int = field(default=0, metadata={"kind": "u2"})
    rev_count: int = field(default=0, metadata={"kind": "u2"})
    watchdog_ms: int = field(default=0, metadata={"kind": "u2"})
    normal_mpacs: int = field(default=0, metadata={"kind": "u1"})
    stall_val: int = field(default=0, metadata={"kind": "u2"})
    stall_count_ms: int = field(default=0, metadata={"kind": "u2"})
    joy_vel_mmps: int = field(default=0, metadata={"kind": "u2"})
    joy_rot_vel_degps: int = field(default=0, metadata={"kind": "u2"})
    rot_vel_max_degps: int = field(default=0, metadata={"kind": "u2"})
    trans_vel_max_mmps: int = field(default=0, metadata={"kind": "u2"})
    rot_accel_degps2: int = field(default=0, metadata={"kind": "u2"})
    rot_decel_degps2: int = field(default=0, metadata={"kind": "u2"})
    rot_kp: int = field(default=0, metadata={"kind": "u2"})
    rot_kv: int = field(default=0, metadata={"kind": "u2"})
    rot_ki: int = field(default=0, metadata={"kind": "u2"})
    trans_accel_mmps2: int = field(default=0, metadata={"kind": "u2"})
    trans_decel_mmps2: int = field(default=0, metadata={"kind": "u2"})
    trans_kp: int = field(default=0, metadata={"kind": "u2"})
    trans_kv: int = field(default=0, metadata={"kind": "u2"})
    trans_ki: int = field(default=0, metadata={"kind": "u2"})
    front_bumps: int = field(default=0, metadata={"kind": "u1"})
    rear_bumps: int = field(default=0, metadata={"kind": "u1"})
    has_charger: int = field(default=0, metadata={"kind": "u1"})
    sonar_cycle_ms: int = field(default=0, metadata={"kind": "u1"})
    reset_baud: int = field(default=0, metadata={"kind": "u1"})  # 2: auto-baud
    gyro_type: int = field(default=0, metadata={"kind": "u1"})
    drift_factor: int = field(default=0, metadata={"kind": "s2"})
    aux2_baud: int = field(default=0, metadata={"kind": "u1"})
    aux3_baud: int = field(default=0, metadata={"kind": "u1"})
    ticks_mm: int = field(default=0, metadata={"kind": "u2"})
    shutdown_voltage_dv: int = field(default=0, metadata={"kind": "u2"})
    firmware_version: str = ""
    gyro_cw: int = field(default=0, metadata={"kind": "u2"})
    gyro_ccw: int = field(default=0, metadata={"kind": "u2"})
    kinematics_delay_ms: int = field(default=0, metadata={"kind": "u1"})
    lat_vel_top_mmps: int = field(default=0, metadata={"kind": "u2"})
    lat_accel_top_mmps2: int = field(default=0, metadata={"kind": "u2"})
    lat_vel_max_mmps: int = field(default=0, metadata={"kind": "u2"})
    lat_accel_mmps2: int = field(default=0, metadata={"kind": "u2"})
    lat_decel_mmps2: int = field(default=0, metadata={"kind": "u2"})
    charge_threshold: int = field(default=0, metadata={"kind": "u2"})
    pdb_port: int = field(default=0, metadata={"kind": "u1"})
    gyro_rate_limit: int = field(default=0, metadata={"kind": "u2"})
    high_temperature_shutdown: int = field(default=0, metadata={"kind": "s1"})
    power_bits: int = field(default=0, metadata={"kind": "u2"})
    battery_type: int = field(default=0, metadata={"kind": "u1"})
    state_of_charge_low: int = field(default=0, metadata={"kind": "u2"})
    state_of_charge_shutdown: int = field(default=0, metadata={"kind": "u2"})
    bootloader_version: str = ""
    config_flags: int = field(default=0, metadata={"kind": "u4"})
    gyro_fw_version: int = field(default=0, metadata={"kind": "s2"})
    fields_read: int = field(default=-1, compare=False, metadata={"kind": "meta"})

    def has(self, name: str) -> bool:
        """Whether field `name` was in the packet (False for fields older firmware omits)."""
        index = FIELD_INDEX[name]
        return self.fields_read < 0 or index < self.fields_read


# (name, kind) in packet order; kind "str" is a NUL-terminated string.
FIELDS: tuple[tuple[str, str], ...] = tuple(
    (f.name, f.metadata.get("kind", "str"))
    for f in fields(RobotConfig)
    if f.metadata.get("kind") != "meta"
)
FIELD_INDEX = {name: i for i, (name, _) in enumerate(FIELDS)}


def encode_config(cfg: RobotConfig) -> bytes:
    """The CONFIG packet's body (type byte first) for `cfg` (robot side); every field.

    ValueError if a value does not fit its field or a string is not NUL-free ASCII.
    """
    body = bytearray((CONFIG_PAC,))
    for (name, kind), value in zip(FIELDS, astuple(cfg), strict=False):
        if kind == "str":
            raw = str(value).encode("ascii")
            if b"\0" in raw:
                raise ValueError(f"CONFIG {name}: a NUL inside {value!r}")
            body += raw + b"\0"
            continue
        try:
            body += struct.pack(_INT_FORMATS[kind], value)
        except struct.error as exc:
            raise ValueError(f"CONFIG {name}={value} does not fit {kind}") from exc
    return bytes(body)


def decode_config(body: bytes) -> RobotConfig:
    """A CONFIG packet body (type byte first) -> RobotConfig, up to where the packet ends.

    ProtocolError if it is not a CONFIG packet or ends before the first three strings.
    """
    if not body or body[0] != CONFIG_PAC:
        raise ProtocolError(f"not a CONFIG packet: type {body[:1].hex() or 'none'}, want 20")
    values: dict[str, object] = {}
    offset = 1
    for name, kind in FIELDS:
        got = _read(body, offset, kind)
        if got is None:
            break
        values[name], offset = got
    if len(values) < FIELD_INDEX["serial"] + 1:
        raise ProtocolError(
            f"CONFIG packet of {len(body)} bytes ends inside its first strings "
            "(want type, subtype and serial number, NUL-terminated)"
        )
    return RobotConfig(**values, fields_read=len(values))  # type: ignore[arg-type]


def _read(body: bytes, offset: int, kind: str) -> tuple[object, int] | None:
    if kind == "str":
        end = body.find(b"\0", offset)
        if end < 0:
            return None
        return body[offset:end].decode("ascii", "replace"), end + 1
    fmt = _INT_FORMATS[kind]
    size = struct.calcsize(fmt)
    if offset + size > len(body):
        return None
    return struct.unpack_from(fmt, body, offset)[0], offset + size
