"""rmw_zenoh's key space as phalanx builds it, against the reference and against an
implementation that is not ours.

The reference is rmw_zenoh's docs/design.md: its examples of data keys and liveliness
tokens are rebuilt here character for character (the type hash of std_msgs/String from
rosbags' type store included), and every key and token of the bridge is taken apart by
the rules of rmw_zenoh's `Entity::make` (liveliness_utils.cpp): '/'-separated parts,
none empty, the `@ros2_lv` admin space, a known entity kind, 9 parts for a node and 13
for a publisher, names demangled ('%' -> '/'). The independent implementation is
ROBOTIS' zenoh-ros2-sdk: its key builders, its RIHS01 hashing of ROS's .msg definitions
and its attachment parser must agree with ours.
"""

from __future__ import annotations

import struct
import time
from pathlib import Path

import pytest
from pydantic import ValidationError

from phalanx.core.config import Ros2Config, Scenario
from phalanx.core.errors import ConfigError
from phalanx.ros2.graph import attachment, gid_of
from phalanx.ros2.names import (
    PUBLISHER,
    SUBSCRIPTION,
    TRANSIENT_LOCAL,
    NodeId,
    Qos,
    data_key,
    distinct_tokens,
    node_token,
    publisher_token,
    qos_text,
    robot_topic,
    ros_token,
)
from phalanx.ros2.topics import fleet_inputs, fleet_topics
from phalanx.ros2.typestore import type_hash

STRING = "std_msgs/msg/String"
# The design document's examples (ROS_DOMAIN_ID 2 for the tokens).
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
CHATTER = f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
CHATTER_NS = f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
LISTENER = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
TALKER_PUB = (
    "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
    f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,"
)
KINDS = {"NN", "MP", "MS", "SS", "SC"}


def test_the_design_documents_examples_come_out_character_for_character() -> None:
    string_hash = type_hash(STRING)
    assert data_key(0, "/chatter", STRING, string_hash) == CHATTER
    assert data_key(0, "/robot1/chatter", STRING, string_hash) == CHATTER_NS
    listener = NodeId(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "/", "listener")
    assert node_token(listener) == LISTENER
    talker = NodeId(2, "8b20917502ee955ac4476e0266340d5c", 0, "/", "talker")
    token = publisher_token(
        talker, 10, topic="/chatter", ros_type=STRING, type_hash=string_hash, qos=Qos(depth=7)
    )
    assert token == TALKER_PUB


def test_the_compact_qos_leaves_rmw_zenohs_defaults_out() -> None:
    assert qos_text(Qos(depth=42)) == "::,:,:,:,,"  # every field at its default
    assert qos_text(Qos(depth=10)) == "::,10:,:,:,,"
    assert qos_text(Qos(depth=1, durability=TRANSIENT_LOCAL)) == ":1:,1:,:,:,,"
    assert qos_text(Qos(depth=5, reliability=2)) == "2::,5:,:,:,,"


def _entity(token: str) -> dict[str, str]:
    """A token taken apart as rmw_zenoh's `Entity::make` does (a failed check asserts)."""
    parts = token.split("/")
    assert all(parts), f"empty part in {token}"
    assert parts[0] == "@ros2_lv"
    assert parts[5] in KINDS
    assert len(parts) == (9 if parts[5] == "NN" else 13)
    fields = ("domain", "zid", "nid", "eid", "kind", "enclave", "namespace", "node")
    entity = dict(zip(fields, parts[1:9], strict=True))
    for name in ("enclave", "namespace", "node"):
        entity[name] = entity[name].replace("%", "/")
    if len(parts) == 13:
        entity |= {"topic": parts[9].replace("%", "/"), "type": parts[10], "hash": parts[11]}
        entity["qos"] = parts[12]
    return entity


def test_every_key_and_token_of_the_bridge_follows_rmw_zenohs_rules(wedge: Scenario) -> None:
    cfg = Ros2Config(namespace="lab", domain_id=7)
    topics = fleet_topics(cfg, [r.id for r in wedge.robots])
    assert {t.name for t in topics} >= {"/lab/r1/odom", "/lab/r3/sonar", "/tf", "/lab/markers"}
    node = NodeId(7, "0123456789abcdef0123456789abcdef", 0, "/lab", "phalanx_bridge")
    assert _entity(node_token(node)) == {
        "domain": "7", "zid": node.zid, "nid": "0", "eid": "0", "kind": "NN", "enclave": "/",
        "namespace": "/lab", "node": "phalanx_bridge",
    }  # fmt: skip
    for entity_id, topic in enumerate(topics, start=1):
        token = publisher_token(
            node, entity_id, topic=topic.name, ros_type=topic.ros_type,
            type_hash=topic.type_hash, qos=topic.qos,
        )  # fmt: skip
        parsed = _entity(token)
        assert parsed["topic"] == topic.name
        assert parsed["hash"] == type_hash(topic.ros_type) == topic.type_hash
        package, kind, name = topic.ros_type.split("/")
        assert parsed["type"] == f"{package}::{kind}::dds_::{name}_"
        key = topic.key(7).split("/")
        assert key[0] == "7"
        assert "/".join(key[1:-2]) == topic.name.strip("/")
        assert key[-2:] == [parsed["type"], parsed["hash"]]


def test_the_bridges_subscriptions_follow_rmw_zenohs_rules() -> None:
    cfg = Ros2Config(namespace="lab", domain_id=7)
    inputs = {t.kind: t for t in fleet_inputs(cfg)}
    assert {k: (t.name, t.ros_type) for k, t in inputs.items()} == {
        "cmd_vel": ("/lab/cmd_vel", "geometry_msgs/msg/Twist"),
        "goal_pose": ("/lab/goal_pose", "geometry_msgs/msg/PoseStamped"),
    }
    node = NodeId(7, "0123456789abcdef0123456789abcdef", 0, "/lab", "phalanx_bridge")
    for entity_id, topic in enumerate(inputs.values(), start=20):
        token = publisher_token(
            node, entity_id, topic=topic.name, ros_type=topic.ros_type,
            type_hash=topic.type_hash, qos=topic.qos, kind=SUBSCRIPTION,
        )  # fmt: skip
        parsed = _entity(token)
        assert (parsed["kind"], parsed["topic"]) == ("MS", topic.name)
        assert parsed["eid"] == str(entity_id)
        assert parsed["hash"] == type_hash(topic.ros_type)
        assert topic.key(7) == f"7/lab/{topic.kind}/{parsed['type']}/{parsed['hash']}"
    assert fleet_inputs(Ros2Config(inputs=())) == []


def test_robot_ids_become_ros_names_and_clashes_are_refused() -> None:
    assert ros_token("r1") == "r1"
    assert ros_token("robot-a") == "robot_a"
    assert ros_token("7") == "_7"  # a ROS name's token never starts with a digit
    assert robot_topic(Ros2Config(), "robot-a", "odom") == "/robot_a/odom"
    with pytest.raises(ConfigError, match="same ROS name"):
        distinct_tokens(["robot-a", "robot_a"])


def test_the_ros2_section_refuses_what_ros_names_cannot_hold() -> None:
    assert Ros2Config().enabled is False  # off unless asked for
    for bad in ({"namespace": "a/b"}, {"namespace": "1x"}, {"node": "my-node"},
                {"topics": ["odom", "laser"]}, {"domain_id": 233}, {"colour": 1}):  # fmt: skip
        with pytest.raises(ValidationError):
            Ros2Config.model_validate(bad)


def test_the_attachment_is_the_documented_33_bytes() -> None:
    gid = gid_of("@ros2_lv/0/x/0/1/MP/%/%/n/%t/std_msgs::msg::dds_::String_/RIHS01_0/::,10:,:,:,,")
    now_ns = time.time_ns()
    raw = attachment(12, now_ns, gid)
    # design.md: int64 LE sequence number, int64 LE ns since the epoch, GID length, GID.
    assert len(raw) == 33
    assert struct.unpack("<qqB", raw[:17]) == (12, now_ns, 16)
    assert raw[17:] == gid
    # What rmw_zenoh's AttachmentData reads: Zenoh's own serialisation of the tuple.
    import zenoh
    from zenoh.ext import Int64, z_deserialize, z_serialize

    assert raw == z_serialize((Int64(12), Int64(now_ns), gid)).to_bytes()
    assert z_deserialize(tuple[Int64, Int64, bytes], zenoh.ZBytes(raw)) == (12, now_ns, gid)
    with pytest.raises(ValueError, match="16 bytes"):
        attachment(1, now_ns, gid[:8])


# --- ROBOTIS' zenoh-ros2-sdk: an implementation of the same key format -----------------------


def test_an_independent_implementation_builds_the_same_keys_and_tokens(wedge: Scenario) -> None:
    from zenoh_ros2_sdk.entity import EndpointEntity, EntityKind, NodeEntity
    from zenoh_ros2_sdk.keyexpr import (
        endpoint_liveliness_keyexpr,
        node_liveliness_keyexpr,
        topic_keyexpr,
    )
    from zenoh_ros2_sdk.utils import ros2_to_dds_type

    cfg = Ros2Config()
    zid = "5c9900519475115121059f8f0c87a514"
    ours = NodeId(0, zid, 3, "/", "phalanx_bridge")
    theirs = NodeEntity(domain_id=0, session_id=zid, node_id=3, node_name="phalanx_bridge")
    assert node_token(ours) == node_liveliness_keyexpr(theirs)
    # what the bridge publishes, then what it takes in (ids of their own)
    entities = [
        *((PUBLISHER, EntityKind.PUBLISHER, i, t) for i, t in enumerate(
            fleet_topics(cfg, [r.id for r in wedge.robots]), 1)),
        *((SUBSCRIPTION, EntityKind.SUBSCRIPTION, i, t) for i, t in enumerate(
            fleet_inputs(cfg), 100)),
    ]  # fmt: skip
    for kind, their_kind, entity_id, topic in entities:
        dds = ros2_to_dds_type(topic.ros_type)
        assert topic.key(0) == topic_keyexpr(0, topic.name, dds, topic.type_hash)
        endpoint = EndpointEntity(
            node=theirs, entity_id=entity_id, kind=their_kind, name=topic.name,
            dds_type_name=dds, type_hash=topic.type_hash, qos=qos_text(topic.qos),
        )  # fmt: skip
        token = publisher_token(
            ours, entity_id, topic=topic.name, ros_type=topic.ros_type,
            type_hash=topic.type_hash, qos=topic.qos, kind=kind,
        )  # fmt: skip
        assert token == endpoint_liveliness_keyexpr(endpoint)


@pytest.mark.parametrize(
    "ros_type",
    [
        "std_msgs/msg/String",
        "geometry_msgs/msg/Twist",
        "nav_msgs/msg/Odometry",
        "geometry_msgs/msg/PoseStamped",
    ],
)
def test_an_independent_rihs01_of_ros_own_definitions_is_ours(
    ros_type: str, msg_folder: Path, sdk_registry: None
) -> None:
    from zenoh_ros2_sdk.message_registry import get_registry
    from zenoh_ros2_sdk.utils import get_type_hash, load_dependencies_recursive

    definition = (msg_folder / f"{ros_type}.msg").read_text(encoding="utf-8")
    dependencies = load_dependencies_recursive(ros_type, definition, get_registry())
    assert get_type_hash(ros_type, definition, dependencies) == type_hash(ros_type)


def test_an_independent_parser_reads_our_attachment() -> None:
    from zenoh_ros2_sdk.attachment import Attachment

    gid = gid_of("a token")
    parsed = Attachment.from_bytes(attachment(3, 1_700_000_000_123_456_789, gid))
    assert (parsed.sequence_id, parsed.timestamp_ns, parsed.gid) == (
        3,
        1_700_000_000_123_456_789,
        gid,
    )
