"""CiA 402 (drives and motion control) as the `canopen` backend and the simulated drives
use it: controlword commands, statusword states, and the object dictionary of a velocity
drive with the PDO mapping we run (RPDO1: controlword + target velocity; TPDO1:
statusword + velocity actual). A real drive's own EDS can replace `drive_od` as long as
it maps the same objects. The CiA 402 facts it follows: docs/HARDWARE.md.
"""

from __future__ import annotations

import io
from enum import IntEnum

import canopen

# Statusword values (CiA 402) of the states we model.
SW_SWITCH_ON_DISABLED = 0x40
SW_READY = 0x21
SW_SWITCHED_ON = 0x23
SW_OPERATION_ENABLED = 0x27
SW_QUICK_STOP = 0x07
SW_FAULT = 0x08
SW_TARGET_REACHED = 0x0400


class Cw(IntEnum):
    """Controlword commands (CiA 402)."""

    DISABLE_VOLTAGE = 0x00
    QUICK_STOP = 0x02
    SHUTDOWN = 0x06
    SWITCH_ON = 0x07
    ENABLE_OPERATION = 0x0F
    FAULT_RESET = 0x80


def drive_eds(node_id: int, heartbeat_ms: int = 50) -> str:
    """EDS text of a CiA 402 velocity drive with RPDO1 (controlword, target velocity) and
    TPDO1 (statusword, velocity actual).
    """
    objects: list[tuple[int, str, int, str, int | str]] = [
        # index, name, data type, access, default
        (0x1000, "Device type", 0x0007, "ro", 0x00020192),
        (0x1001, "Error register", 0x0005, "ro", 0),
        (0x1017, "Producer heartbeat time", 0x0006, "rw", heartbeat_ms),
        (0x603F, "Error code", 0x0006, "ro", 0),
        (0x6040, "Controlword", 0x0006, "rw", 0),
        (0x6041, "Statusword", 0x0006, "ro", SW_SWITCH_ON_DISABLED),
        (0x6060, "Modes of operation", 0x0002, "rw", 0),
        (0x6061, "Modes of operation display", 0x0002, "ro", 0),
        (0x606C, "Velocity actual value", 0x0004, "ro", 0),
        (0x607F, "Max profile velocity", 0x0007, "rw", 100000),
        (0x6083, "Profile acceleration", 0x0007, "rw", 10000),
        (0x6084, "Profile deceleration", 0x0007, "rw", 10000),
        (0x6085, "Quick stop deceleration", 0x0007, "rw", 50000),
        (0x60FF, "Target velocity", 0x0004, "rw", 0),
        (0x6502, "Supported drive modes", 0x0007, "ro", 0x00000004 | 0x00000040),
    ]
    records = {
        0x1400: ("RPDO1 communication parameter", [(0x0007, 0x200 + node_id), (0x0005, 255)]),
        0x1600: ("RPDO1 mapping parameter", [(0x0007, 0x60400010), (0x0007, 0x60FF0020)]),
        0x1800: ("TPDO1 communication parameter", [(0x0007, 0x180 + node_id), (0x0005, 255)]),
        0x1A00: ("TPDO1 mapping parameter", [(0x0007, 0x60410010), (0x0007, 0x606C0020)]),
    }
    out = io.StringIO()
    out.write("[FileInfo]\nFileName=phalanx_cia402.eds\nFileVersion=1\n")
    out.write("[DeviceInfo]\nVendorName=phalanx\nProductName=Simulated CiA 402 drive\n")
    for index, name, dtype, access, default in objects:
        out.write(
            f"[{index:04X}]\nParameterName={name}\nObjectType=0x7\nDataType=0x{dtype:04X}\n"
            f"AccessType={access}\nDefaultValue={default}\nPDOMapping=1\n"
        )
    for index, (name, subs) in records.items():
        out.write(
            f"[{index:04X}]\nParameterName={name}\nObjectType=0x9\nSubNumber={len(subs) + 1}\n"
        )
        out.write(
            f"[{index:04X}sub0]\nParameterName=Highest sub-index supported\nObjectType=0x7\n"
            f"DataType=0x0005\nAccessType=ro\nDefaultValue={len(subs)}\nPDOMapping=0\n"
        )
        for sub, (dtype, default) in enumerate(subs, start=1):
            out.write(
                f"[{index:04X}sub{sub}]\nParameterName=Entry {sub}\nObjectType=0x7\n"
                f"DataType=0x{dtype:04X}\nAccessType=rw\nDefaultValue={default}\nPDOMapping=0\n"
            )
    return out.getvalue()


def drive_od(node_id: int, heartbeat_ms: int = 50) -> canopen.ObjectDictionary:
    """The object dictionary of `drive_eds`."""
    source = io.StringIO(drive_eds(node_id, heartbeat_ms))
    source.name = "phalanx_cia402.eds"  # the importer picks the format by the name
    return canopen.import_od(source, node_id)
