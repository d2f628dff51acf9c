"""ROS names and rmw_zenoh's key expressions, built in one place.

rmw_zenoh (its docs/design.md and `liveliness_utils.cpp`) maps ROS 2 onto Zenoh thus:

- a topic's data travels on `<domain_id>/<fully qualified name, no leading or trailing
  '/'>/<DDS type name>/<type hash>`, e.g.
  `0/r1/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_3cc9...`;
- every node, publisher and subscription holds a liveliness token under the admin
  space `@ros2_lv` (a verbatim chunk: `*` and `**` never match it):
  `@ros2_lv/<domain>/<session id>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/
  <node name>` for a node (`NN`, its entity id is its node id), and for a publisher
  (`MP`) or a subscription (`MS`) the same followed by `/<topic>/<DDS type name>/
  <type hash>/<qos>`, each name "mangled": every '/' replaced by '%' (an empty
  namespace is `%`);
- the QoS is written compactly (`qos_text`): only what differs from rmw_zenoh's
  defaults (reliable, volatile, keep last 42, infinite deadline, lifespan and lease).

Nothing here needs ROS 2 or `rosbags`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Final, Literal

from phalanx.core.config import Ros2Config
from phalanx.core.errors import ConfigError

ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION = "NN", "MP", "MS"
# rmw_zenoh's default QoS, which the compact form leaves out (qos.cpp).
DEFAULT_DEPTH = 42
RELIABLE: Final = 1  # rmw's RMW_QOS_POLICY_RELIABILITY_RELIABLE
BEST_EFFORT: Final = 2
TRANSIENT_LOCAL: Final = 1  # RMW_QOS_POLICY_DURABILITY_TRANSIENT_LOCAL
VOLATILE: Final = 2
_TOKEN = re.compile(r"[^A-Za-z0-9_]")


@dataclass(frozen=True)
class Qos:
    """A publisher's QoS, as far as rmw_zenoh's token and the bag's metadata carry it."""

    depth: int = 10
    reliability: Literal[1, 2] = RELIABLE
    durability: Literal[1, 2] = VOLATILE

    @property
    def transient_local(self) -> bool:
        """Whether late subscribers get the last messages (`/tf_static`)."""
        return self.durability == TRANSIENT_LOCAL


def qos_text(qos: Qos) -> str:
    """rmw_zenoh's compact QoS: `<reliability>:<durability>:<history>,<depth>:<deadline s>,
    <ns>:<lifespan s>,<ns>:<liveliness>,<lease s>,<ns>`, each field empty at its default
    (`::,10:,:,:,,` for depth 10; keep-last history and the infinite times are defaults).
    """
    reliability = "" if qos.reliability == RELIABLE else str(qos.reliability)
    durability = "" if qos.durability == VOLATILE else str(qos.durability)
    depth = "" if qos.depth == DEFAULT_DEPTH else str(qos.depth)
    return f"{reliability}:{durability}:,{depth}:,:,:,,"


def ros_token(name: str) -> str:
    """`name` as one token of a ROS name: letters, digits and '_' (every other character
    becomes '_'), never a digit first (then '_' is put before it).
    """
    token = _TOKEN.sub("_", name)
    return f"_{token}" if token[:1].isdigit() else token


def fleet_namespace(cfg: Ros2Config) -> str:
    """The bridge node's namespace: `/` or `/<namespace>`."""
    return f"/{cfg.namespace}" if cfg.namespace else "/"


def robot_namespace(cfg: Ros2Config, robot_id: str) -> str:
    """Robot `robot_id`'s namespace: `/r1`, or `/<namespace>/r1`."""
    return f"{fleet_namespace(cfg).rstrip('/')}/{ros_token(robot_id)}"


def robot_topic(cfg: Ros2Config, robot_id: str, name: str) -> str:
    """The fully qualified name of a robot's topic: `/r1/odom`."""
    return f"{robot_namespace(cfg, robot_id)}/{name}"


def fleet_topic(cfg: Ros2Config, name: str) -> str:
    """The fully qualified name of a topic of the whole fleet in its namespace."""
    return f"{fleet_namespace(cfg).rstrip('/')}/{name}"


def robot_frame(robot_id: str, frame: str = "base_link") -> str:
    """A robot's TF frame: `r1/base_link`, `r1/sonar_3`."""
    return f"{ros_token(robot_id)}/{frame}"


def distinct_tokens(robot_ids: list[str]) -> None:
    """ConfigError if two robots' ids become the same ROS name (`r-1` and `r_1`)."""
    seen: dict[str, str] = {}
    for rid in robot_ids:
        token = ros_token(rid)
        if token in seen:
            raise ConfigError(
                f"robots {seen[token]!r} and {rid!r} have the same ROS name {token!r}: "
                "ROS names hold only letters, digits and '_'"
            )
        seen[token] = rid


def dds_type_name(ros_type: str) -> str:
    """The type's name as rmw_zenoh puts it in keys: `nav_msgs/msg/Odometry` ->
    `nav_msgs::msg::dds_::Odometry_`.
    """
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    """A name as one chunk of a liveliness token: every '/' replaced by '%'."""
    return name.replace("/", "%")


def data_key(domain_id: int, topic: str, ros_type: str, type_hash: str) -> str:
    """Where a topic's messages travel: `<domain>/<topic>/<DDS type name>/<type hash>`."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(ros_type)}/{type_hash}"


@dataclass(frozen=True)
class NodeId:
    """A node in the ROS graph: its domain, the Zenoh session (`zid`) that holds it, its
    id within that session, namespace and name.
    """

    domain_id: int
    zid: str
    node_id: int
    namespace: str
    name: str
    enclave: str = "/"

    def prefix(self, entity_id: int, kind: str) -> str:
        """The token's part up to the node's name, for entity `entity_id` of `kind`."""
        return (
            f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/{self.node_id}/{entity_id}/{kind}/"
            f"{mangle(self.enclave)}/{mangle(self.namespace)}/{mangle(self.name)}"
        )


def node_token(node: NodeId) -> str:
    """The node's own liveliness token (its entity id is its node id)."""
    return node.prefix(node.node_id, NODE)


def publisher_token(
    node: NodeId, entity_id: int, *, topic: str, ros_type: str, type_hash: str, qos: Qos,
    kind: str = PUBLISHER,
) -> str:  # fmt: skip
    """A publisher's liveliness token (a subscription's with `kind` `SUBSCRIPTION`): the
    node's part, then topic, type, hash and QoS.
    """
    tail = f"{mangle(topic)}/{dds_type_name(ros_type)}/{type_hash}/{qos_text(qos)}"
    return f"{node.prefix(entity_id, kind)}/{tail}"


def publisher_token_pattern(
    node_name: str, namespace: str, domain_id: int, *, topic: str, ros_type: str, type_hash: str,
    qos: Qos, kind: str = PUBLISHER,
) -> str:  # fmt: skip
    """Every token a publisher (or, `kind` `SUBSCRIPTION`, a subscription) of this node
    could hold, whatever its session and ids: the session, node and entity ids as `*`
    (what an access rule allows).
    """
    node = NodeId(domain_id, "*", 0, namespace, node_name)
    token = publisher_token(
        node, 0, topic=topic, ros_type=ros_type, type_hash=type_hash, qos=qos, kind=kind
    )
    return _wild_ids(token)


def node_token_pattern(node_name: str, namespace: str, domain_id: int) -> str:
    """Every token this node could hold, whatever its session and id."""
    return _wild_ids(node_token(NodeId(domain_id, "*", 0, namespace, node_name)))


def _wild_ids(token: str) -> str:
    parts = token.split("/")
    parts[3] = parts[4] = "*"  # node id, entity id (the session id is `*` already)
    return "/".join(parts)
