"""ROS 2 message types from `rosbags` (its type store of a ROS 2 distribution): the
message classes, their RIHS01 type hashes (REP-2016, as rosidl computes them: rosbags'
`hash_rihs01`) and CDR (de)serialisation with the encapsulation header rmw_zenoh and
rosbag2 carry. No byte layout is written by hand here.

`rosbags` is imported on first use; without it a `ConfigError` says how to install it.
"""

from __future__ import annotations

from functools import cache
from typing import TYPE_CHECKING, Any, Literal

from phalanx.core.errors import ConfigError

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

Distro = Literal["jazzy", "kilted"]
INSTALL_HINT = "ROS 2 support needs rosbags: pip install 'phalanx[ros2]'"


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


def to_cdr(message: Any, ros_type: str, distro: Distro = "jazzy") -> bytes:
    """`message` as little-endian CDR, encapsulation header first."""
    return bytes(store(distro).serialize_cdr(message, ros_type))


def from_cdr(payload: bytes, ros_type: str, distro: Distro = "jazzy") -> Any:
    """A CDR payload back as a message of `ros_type`."""
    return store(distro).deserialize_cdr(payload, ros_type)
