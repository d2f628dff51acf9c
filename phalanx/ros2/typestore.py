"""ROS 2 message types from `rosbags` (its type store of a ROS 2 distribution): the
message classes, their RIHS01 type hashes (REP-2016, as rosidl computes them: rosbags'
`hash_rihs01`) and CDR (de)serialisation with the encapsulation header rmw_zenoh and
rosbag2 carry. No byte layout is written by hand here: a `CdrTemplate` finds where a
message's numbers lie by having rosbags write it with probe values.

`rosbags` is imported on first use; without it a `ConfigError` says how to install it.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from functools import cache
from operator import attrgetter
from typing import TYPE_CHECKING, Any, Literal

from phalanx.core.errors import ConfigError

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

Distro = Literal["jazzy", "kilted"]
INSTALL_HINT = "ROS 2 support needs rosbags: pip install 'phalanx[ros2]'"
# The encapsulation header: CDR_LE, no options.
_LITTLE_ENDIAN = b"\x00\x01\x00\x00"
_HEADER_SIZE = len(_LITTLE_ENDIAN)
# ROS's fixed-size numbers as `struct` packs them.
_NUMBERS = {
    "float64": "d", "float32": "f", "int64": "q", "uint64": "Q", "int32": "i",
    "uint32": "I", "int16": "h", "uint16": "H", "int8": "b", "uint8": "B",
}  # fmt: skip


@cache
def store(distro: Distro = "jazzy") -> Typestore:
    """The type store of ROS 2 `distro` (loaded once)."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:
        raise ConfigError(INSTALL_HINT) from exc
    stores = {"jazzy": Stores.ROS2_JAZZY, "kilted": Stores.ROS2_KILTED}
    return get_typestore(stores[distro])


@cache
def type_hash(ros_type: str, distro: Distro = "jazzy") -> str:
    """`RIHS01_<sha256 hex>` of `ros_type` (e.g. `nav_msgs/msg/Odometry`) in `distro`."""
    return str(store(distro).hash_rihs01(ros_type))


def message_class(ros_type: str, distro: Distro = "jazzy") -> Any:
    """The dataclass of `ros_type`, to build a message with."""
    return store(distro).types[ros_type]


class CdrWriter:
    """Messages of one type as little-endian CDR, encapsulation header first: rosbags'
    serialiser of the type (what `Typestore.serialize_cdr` runs), looked up once.
    """

    def __init__(self, ros_type: str, distro: Distro = "jazzy") -> None:
        self._store = store(distro)
        msgdef = self._store.get_msgdef(ros_type)
        self._size, self._write = msgdef.getsize_cdr, msgdef.serialize_cdr_le

    def __call__(self, message: Any) -> bytearray:
        """`message`'s CDR bytes."""
        out = bytearray(_HEADER_SIZE + self._size(0, message, self._store))
        out[:_HEADER_SIZE] = _LITTLE_ENDIAN
        end = self._write(memoryview(out)[_HEADER_SIZE:], 0, message, self._store)
        if end + _HEADER_SIZE != len(out):
            raise ValueError(f"CDR of {message!r}: {end} bytes written, not {len(out)}")
        return out


@cache
def cdr_writer(ros_type: str, distro: Distro = "jazzy") -> CdrWriter:
    """The CDR writer of `ros_type` (made once)."""
    return CdrWriter(ros_type, distro)


class CdrTemplate:
    """The CDR of a message of which only some numbers change (`fields`: dotted paths to
    a number or a fixed-size array of numbers, e.g. `header.stamp.sec`,
    `pose.covariance`), and the bytes of one byte sequence (`tail`, e.g. a point cloud's
    `data`: empty in `blank`, with nothing after it that its length could shift), its
    strings and other sequences staying as they are in `blank`. rosbags writes `blank`
    once, and once more per field with a probe value in it: where the probe's bytes land,
    and nothing else changed, is where the field lies (else a ValueError); the tail is
    probed with each length from 1 to 8 bytes. A message is then `blank`'s bytes with
    the values packed in and the tail's bytes after their length.
    """

    def __init__(
        self, blank: Any, ros_type: str, fields: Sequence[str], distro: Distro = "jazzy",
        *, tail: str | None = None,
    ) -> None:  # fmt: skip
        write = cdr_writer(ros_type, distro)
        written = bytes(write(blank))
        at = len(written) if tail is None else _tail_at(blank, tail, written, write)
        self._head, self._rest = written[:at], written[at + _LENGTH.size :]
        self._tail = tail is not None
        self._slots = [
            _locate(blank, field, written, write, _number(ros_type, field, distro))
            for field in fields
        ]
        if any(offset + packer.size > at for offset, packer, _ in self._slots):
            raise ValueError(f"{ros_type}: a field lies after the tail {tail!r}")

    def __call__(self, values: Sequence[Any], tail: bytes = b"") -> bytearray:
        """The CDR bytes with `values` (one per field, in order: a number, or a sequence
        of numbers for an array) in place of the blank's, and `tail`'s bytes.
        """
        out = bytearray(self._head)
        for (offset, packer, array), value in zip(self._slots, values, strict=True):
            if array:
                packer.pack_into(out, offset, *value)
            else:
                packer.pack_into(out, offset, value)
        if self._tail:
            out += _LENGTH.pack(len(tail))
            out += tail
            out += self._rest
        return out


_LENGTH = struct.Struct("<I")  # a sequence's length


def _tail_at(blank: Any, tail: str, written: bytes, write: CdrWriter) -> int:
    """Where, in `written` (`blank`'s CDR), the length of byte sequence `tail` lies."""
    import numpy as np

    def probed(probe: bytes) -> bytes:
        with _probing(blank, tail, np.frombuffer(probe, dtype=np.uint8)):
            return bytes(write(blank))

    at = probed(bytes(range(0x11, 0x31))).find(bytes(range(0x11, 0x31))) - _LENGTH.size
    head, rest = written[:at], written[at + _LENGTH.size :]
    # Lengths 1 to 8: any padding after the tail (what follows aligned) would show.
    for probe in (bytes(range(0x11, 0x11 + size)) for size in range(1, 9)):
        if at < 0 or probed(probe) != head + _LENGTH.pack(len(probe)) + probe + rest:
            raise ValueError(f"{tail}: not a byte sequence with nothing after it to shift")
    return at


@contextmanager
def _probing(blank: Any, field: str, value: Any) -> Iterator[None]:
    """`blank` with `field` (a dotted path) set to `value` for a while."""
    *parents, name = field.split(".")
    owner = blank
    for part in parents:
        owner = getattr(owner, part)
    before = getattr(owner, name)
    setattr(owner, name, value)
    try:
        yield
    finally:
        setattr(owner, name, before)


def _number(ros_type: str, field: str, distro: Distro) -> tuple[struct.Struct, bool]:
    """How field `field` of `ros_type` is packed; whether it is an array."""
    from rosbags.interfaces import Nodetype

    fielddefs = store(distro).fielddefs
    *parents, name = field.split(".")
    for part in parents:
        ros_type = _field_of(fielddefs[ros_type][1], part, field)[1]
    kind, detail = _field_of(fielddefs[ros_type][1], name, field)
    array = kind == Nodetype.ARRAY
    count = 1
    if array:
        (kind, detail), count = detail
    if kind != Nodetype.BASE or detail[0] not in _NUMBERS:
        raise ValueError(f"{field} is not a number or a fixed-size array of numbers")
    return struct.Struct(f"<{count}{_NUMBERS[detail[0]]}"), array


def _field_of(defs: list[tuple[str, Any]], name: str, field: str) -> Any:
    for candidate, desc in defs:
        if candidate == name:
            return desc
    raise ValueError(f"{field}: no field {name!r}")


def _locate(
    blank: Any, field: str, written: bytes, write: CdrWriter, number: tuple[struct.Struct, bool]
) -> tuple[int, struct.Struct, bool]:
    """Where in `written` (`blank`'s CDR) field `field` lies: (offset, packer, array)."""
    packer, array = number
    probe = bytes(0x11 + i % 0x5F for i in range(packer.size))  # no NaN nor infinity
    values = packer.unpack(probe)
    if array:
        value = _like(attrgetter(field)(blank), values)
    else:
        (value,) = values
    with _probing(blank, field, value):
        probed = bytes(write(blank))
    offset = probed.find(probe)
    end = offset + packer.size
    if (
        offset < 0
        or probed.find(probe, offset + 1) >= 0
        or probed[:offset] + probed[end:] != written[:offset] + written[end:]
    ):
        raise ValueError(f"{field}: its bytes are not in one place of the CDR")
    return offset, packer, array


def _like(array: Any, values: Sequence[Any]) -> Any:
    """`values` as an array of `array`'s dtype (rosbags' fixed-size arrays are numpy's)."""
    import numpy as np

    return np.asarray(values, dtype=array.dtype)


def to_cdr(message: Any, ros_type: str, distro: Distro = "jazzy") -> bytes:
    """`message` as little-endian CDR, encapsulation header first."""
    return bytes(cdr_writer(ros_type, distro)(message))


def from_cdr(payload: bytes, ros_type: str, distro: Distro = "jazzy") -> Any:
    """A CDR payload back as a message of `ros_type`."""
    return store(distro).deserialize_cdr(payload, ros_type)
