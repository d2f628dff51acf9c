"""The ROS topics of a fleet: names, message types and QoS, one list that the bridge
publishes, the MCAP export writes and a deployment's access rules allow.

Per robot, in its namespace (`/r1/...`): `odom` (nav_msgs/Odometry: pose in the map frame,
the twist it drives), `sonar` (sensor_msgs/PointCloud2: its sonar ring's echoes in its
`base_link` frame), `cmd_vel_out` (geometry_msgs/Twist: the command it sends, after its
limiter), `state` (std_msgs/String: its behaviour state). For the fleet: `/tf` (map ->
`rN/base_link`), `/tf_static` (`rN/base_link` -> `rN/sonar_<i>`, the sonar mounts of
the robot's parameter file; transient local) and `markers` in the fleet's namespace
(visualization_msgs/MarkerArray: the formation's slots and the world's obstacles).

What the bridge takes from ROS 2, in the fleet's namespace: `cmd_vel` (geometry_msgs/
Twist, an operator's twist for the robot that leads, as teleop tools send it) and
`goal_pose` (geometry_msgs/PoseStamped, as RViz's goal tool sends it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

from phalanx.core.config import Ros2Config, Ros2Input, Ros2Topic
from phalanx.ros2.names import (
    PUBLISHER,
    SUBSCRIPTION,
    TRANSIENT_LOCAL,
    Qos,
    data_key,
    distinct_tokens,
    fleet_namespace,
    fleet_topic,
    node_token_pattern,
    publisher_token_pattern,
    robot_topic,
)
from phalanx.ros2.typestore import type_hash

ROS_TYPES: Final[dict[Ros2Topic, str]] = {
    "odom": "nav_msgs/msg/Odometry",
    "sonar": "sensor_msgs/msg/PointCloud2",
    "cmd_vel_out": "geometry_msgs/msg/Twist",
    "state": "std_msgs/msg/String",
    "tf": "tf2_msgs/msg/TFMessage",
    "tf_static": "tf2_msgs/msg/TFMessage",
    "markers": "visualization_msgs/msg/MarkerArray",
}
ROBOT_TOPICS: Final[tuple[Ros2Topic, ...]] = ("odom", "sonar", "cmd_vel_out", "state")
INPUT_TYPES: Final[dict[Ros2Input, str]] = {
    "cmd_vel": "geometry_msgs/msg/Twist",
    "goal_pose": "geometry_msgs/msg/PoseStamped",
}
# tf2's own choices: a dynamic broadcaster keeps 100, a static one 1, transient local.
QOS: Final[dict[Ros2Topic, Qos]] = {
    "tf": Qos(depth=100),
    "tf_static": Qos(depth=1, durability=TRANSIENT_LOCAL),
}


@dataclass(frozen=True)
class RosTopic:
    """One topic the fleet has in ROS 2."""

    kind: Ros2Topic | Ros2Input
    name: str  # fully qualified: /r1/odom
    ros_type: str
    type_hash: str
    qos: Qos
    robot_id: str = ""  # "" for the fleet's topics

    def key(self, domain_id: int) -> str:
        """Where its messages travel (rmw_zenoh's data key)."""
        return data_key(domain_id, self.name, self.ros_type, self.type_hash)


def fleet_topics(cfg: Ros2Config, robot_ids: list[str]) -> list[RosTopic]:
    """Every topic `cfg.topics` asks for, for robots `robot_ids` (robot topics first, in
    the robots' order). ConfigError if two robots would share a ROS name.
    """
    distinct_tokens(robot_ids)
    out = [
        _topic(cfg, kind, robot_topic(cfg, rid, kind), rid)
        for rid in robot_ids
        for kind in ROBOT_TOPICS
        if kind in cfg.topics
    ]
    names = {"tf": "/tf", "tf_static": "/tf_static", "markers": fleet_topic(cfg, "markers")}
    out += [_topic(cfg, kind, name, "") for kind, name in names.items() if kind in cfg.topics]
    return out


def fleet_inputs(cfg: Ros2Config) -> list[RosTopic]:
    """Every topic the bridge takes from ROS 2 (`cfg.inputs`), in the fleet's namespace."""
    return [
        RosTopic(
            kind,
            fleet_topic(cfg, kind),
            INPUT_TYPES[kind],
            type_hash(INPUT_TYPES[kind], cfg.distro),
            Qos(),
        )
        for kind in cfg.inputs
    ]


@dataclass(frozen=True)
class BridgeKeys:
    """The key expressions of a bridge of these topics (what access rules allow): its
    data keys (`put`), its node's, publishers' and subscriptions' liveliness tokens,
    whatever its session and ids (`tokens`), under each transient-local topic's key the
    Zenoh advanced publisher's own keys (`caches`: its cache's queryable and replies, its
    detection token and heartbeat, `<key>/@adv/pub/...`), and the data keys of what it
    takes from ROS 2 (`inputs`).
    """

    puts: tuple[str, ...]
    tokens: tuple[str, ...]
    caches: tuple[str, ...]
    inputs: tuple[str, ...] = ()

    def all(self) -> tuple[str, ...]:
        """Every key expression above."""
        return (*self.puts, *self.tokens, *self.caches, *self.inputs)


def bridge_keys(cfg: Ros2Config, robot_ids: list[str]) -> BridgeKeys:
    """The keys of a bridge configured by `cfg` for robots `robot_ids`."""
    topics = fleet_topics(cfg, robot_ids)
    namespace = fleet_namespace(cfg)
    inputs = fleet_inputs(cfg)
    tokens = [node_token_pattern(cfg.node, namespace, cfg.domain_id)]
    tokens += [
        publisher_token_pattern(
            cfg.node, namespace, cfg.domain_id, topic=t.name, ros_type=t.ros_type,
            type_hash=t.type_hash, qos=t.qos, kind=kind,
        )
        for kind, group in ((PUBLISHER, topics), (SUBSCRIPTION, inputs))
        for t in group
    ]  # fmt: skip
    caches = [f"{t.key(cfg.domain_id)}/@adv/pub/**" for t in topics if t.qos.transient_local]
    return BridgeKeys(
        tuple(t.key(cfg.domain_id) for t in topics),
        tuple(tokens),
        tuple(caches),
        tuple(t.key(cfg.domain_id) for t in inputs),
    )


def _topic(cfg: Ros2Config, kind: Ros2Topic, name: str, robot_id: str) -> RosTopic:
    ros_type = ROS_TYPES[kind]
    qos = QOS.get(kind, Qos())
    return RosTopic(kind, name, ros_type, type_hash(ros_type, cfg.distro), qos, robot_id)
