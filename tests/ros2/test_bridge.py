"""The bridge on real Zenoh sessions (loopback, multicast scouting off): robots' messages
go in on phalanx's keys, and a separate session that knows only rmw_zenoh's key format
(built here from the design document's rule, the type hash from rosbags' type store)
takes what comes out and decodes it with rosbags' CDR deserialiser: every message of the
right type with the right values, every sample with rmw_zenoh's attachment, the node and
its publishers in the ROS graph, `/tf_static` served to a late subscriber from the cache,
what the robots send checked on the bridge's thread and the newest kept. The CDR the
bridge writes from templates is what rosbags writes of the same messages. Last, ROBOTIS'
zenoh-ros2-sdk (its own graph discovery, its own subscriber) sees the topics and decodes
a robot's odometry.
"""

from __future__ import annotations

import math
import random
import struct
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
import zenoh
from fleetlab import wait_for
from rosbags.typesys import Stores, get_typestore

from phalanx.core.config import Ros2Config, Scenario
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.robot_params import RobotParams
from phalanx.ros2.bridge import RING_PER_ROBOT, Bridge
from phalanx.ros2.messages import RobotMessages, RosMessages
from phalanx.ros2.typestore import CdrTemplate, message_class
from phalanx.wire.codec import encode
from phalanx.wire.keys import robot_key
from phalanx.wire.messages import Message, RobotState, ScanMessage, SenseFrame
from phalanx.wire.transport import (
    FleetSession,
    TransportConfig,
    free_tcp_port,
    loopback_endpoint,
    open_session,
    zenoh_config,
)

FLEET = "ros"
WAIT_S = 10.0
ROSBAGS = get_typestore(Stores.ROS2_JAZZY)  # theirs: type hashes and the CDR deserialiser
R1_COV = (0.04, 0.01, 0.002, 0.09, -0.003, 0.01)  # xx, xy, xt, yy, yt, tt


def rmw_key(topic: str, ros_type: str, domain_id: int = 0) -> str:
    """rmw_zenoh's data key, by design.md's rule, with rosbags' type hash."""
    package, kind, name = ros_type.split("/")
    dds = f"{package}::{kind}::dds_::{name}_"
    return f"{domain_id}/{topic.strip('/')}/{dds}/{ROSBAGS.hash_rihs01(ros_type)}"


@dataclass
class Heard:
    """What arrived on one rmw_zenoh key: (payload, attachment bytes, arrival ns)."""

    samples: list[tuple[bytes, bytes, int]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def put(self, sample: Any) -> None:
        extra = sample.attachment.to_bytes() if sample.attachment is not None else b""
        with self.lock:
            self.samples.append((sample.payload.to_bytes(), extra, time.time_ns()))

    def decoded(self, ros_type: str) -> list[Any]:
        with self.lock:
            return [ROSBAGS.deserialize_cdr(p, ros_type) for p, _, _ in self.samples]


@dataclass
class Lab:
    """A bridge, the robots' session and a plain Zenoh session on rmw_zenoh's keys."""

    bridge: Bridge
    hub: FleetSession  # the bridge's session
    robots: FleetSession
    ros: Any
    port: int

    def listen(self, topic: str, ros_type: str) -> Heard:
        heard = Heard()
        self.ros.declare_subscriber(rmw_key(topic, ros_type), heard.put)
        return heard

    def send(self, topic: str, message: Message) -> None:
        self.robots.publish(robot_key(FLEET, message.robot_id, topic), message)  # type: ignore[attr-defined]

    def rounds_until(self, done: Callable[[], bool]) -> bool:
        """Bridge rounds until `done` (bounded)."""

        def round_done() -> bool:
            self.bridge.round()
            return done()

        return wait_for(round_done, WAIT_S, poll_s=0.05)


@contextmanager
def lab(wedge: Scenario, p3dx: RobotParams, cfg: Ros2Config | None = None) -> Iterator[Lab]:
    port = free_tcp_port()
    endpoint = loopback_endpoint(port)
    with ExitStack() as stack:
        hub = stack.enter_context(open_session(TransportConfig(listen=(endpoint,))))
        robots = stack.enter_context(open_session(TransportConfig(connect=(endpoint,))))
        ros = zenoh.open(zenoh_config(TransportConfig(connect=(endpoint,))))
        stack.callback(ros.close)
        bridge = Bridge(hub, fleet=FLEET, scenario=wedge, robot=p3dx, cfg=cfg or wedge.ros2)
        yield Lab(bridge, hub, robots, ros, port)


def state(rid: str, seq: int, **values: Any) -> RobotState:
    fields = {"robot_id": rid, "seq": seq, "stamp_s": 0.1 * seq, "x_m": 1.0, "y_m": 2.0,
              "theta_rad": 0.5, "v_mps": 0.15, "omega_radps": 0.05,
              "fsm_state": "FORMATION_TRACK", "formation_leader_id": "r1"}  # fmt: skip
    if rid != "r1":
        fields["leader_id"] = "r1"
    return RobotState.model_validate(fields | values)


def test_odometry_command_state_and_tf_decode_to_what_the_robots_published(
    wedge: Scenario, p3dx: RobotParams
) -> None:
    with lab(wedge, p3dx) as it:
        odom = it.listen("/r1/odom", "nav_msgs/msg/Odometry")
        odom2 = it.listen("/r2/odom", "nav_msgs/msg/Odometry")
        cmd = it.listen("/r1/cmd_vel_out", "geometry_msgs/msg/Twist")
        said = it.listen("/r2/state", "std_msgs/msg/String")
        tf = it.listen("/tf", "tf2_msgs/msg/TFMessage")
        time.sleep(0.3)  # the subscriptions reach the bridge's session
        before = time.time_ns()
        for seq in (1, 2, 3):
            it.send("state", state("r1", seq, x_m=1.0 + seq, cov=R1_COV))
            it.send("state", state("r2", seq, x_m=-1.0, y_m=0.5, theta_rad=-2.5, fsm_state="HOLD"))
            assert it.rounds_until(lambda s=seq: len(odom.samples) >= s and len(odom2.samples) >= s)
        time.sleep(0.2)
        assert it.rounds_until(lambda: len(cmd.samples) >= 3 and len(tf.samples) >= 3)

    last = odom.decoded("nav_msgs/msg/Odometry")[-1]
    assert (last.header.frame_id, last.child_frame_id) == ("map", "r1/base_link")
    assert (last.header.stamp.sec, last.header.stamp.nanosec) == (0, 300_000_000)
    p, q = last.pose.pose.position, last.pose.pose.orientation
    assert (p.x, p.y, p.z) == (4.0, 2.0, 0.0)
    assert (q.x, q.y) == (0.0, 0.0)
    assert 2 * math.atan2(q.z, q.w) == pytest.approx(0.5)
    assert (last.twist.twist.linear.x, last.twist.twist.angular.z) == (0.15, 0.05)
    cov = last.pose.covariance.reshape(6, 6)  # rows x, y, z, roll, pitch, yaw
    xx, xy, xt, yy, yt, tt = R1_COV
    assert (cov[0, 0], cov[0, 1], cov[1, 0], cov[1, 1]) == (xx, xy, xy, yy)
    assert (cov[0, 5], cov[5, 0], cov[1, 5], cov[5, 5]) == (xt, xt, yt, tt)
    assert cov[2:5].sum() == 0.0
    r2 = odom2.decoded("nav_msgs/msg/Odometry")[-1]
    assert r2.pose.covariance.sum() == 0.0  # a robot without an estimator sends none
    assert 2 * math.atan2(r2.pose.pose.orientation.z, r2.pose.pose.orientation.w) == pytest.approx(
        -2.5
    )
    twist = cmd.decoded("geometry_msgs/msg/Twist")[-1]
    assert (twist.linear.x, twist.linear.y, twist.angular.z) == (0.15, 0.0, 0.05)
    assert {m.data for m in said.decoded("std_msgs/msg/String")} == {"HOLD"}
    frames = {
        t.child_frame_id: t for m in tf.decoded("tf2_msgs/msg/TFMessage") for t in m.transforms
    }
    assert {t.header.frame_id for t in frames.values()} == {"map"}
    assert frames["r2/base_link"].transform.translation.x == -1.0
    _attachments_are_rmw_zenohs(odom, before)
    _attachments_are_rmw_zenohs(cmd, before)
    assert odom.samples[0][1][17:] != cmd.samples[0][1][17:]  # a GID per publisher


def _attachments_are_rmw_zenohs(heard: Heard, since_ns: int) -> None:
    """Sequence numbers 1, 2, ..., source stamps of this run, one 16-byte GID."""
    parsed = [(*struct.unpack("<qqB", extra[:17]), extra[17:]) for _, extra, _ in heard.samples]
    assert [seq for seq, *_ in parsed] == list(range(1, len(parsed) + 1))
    assert all(
        since_ns <= stamp <= at
        for (_, stamp, _, _), (_, _, at) in zip(parsed, heard.samples, strict=True)
    )
    assert {(n, len(gid)) for _, _, n, gid in parsed} == {(16, 16)}
    assert len({gid for *_, gid in parsed}) == 1


def test_the_sonar_ring_is_a_point_cloud_of_echoes_in_the_robots_frame(
    wedge: Scenario, p3dx: RobotParams
) -> None:
    ranges = tuple(0.5 + 0.1 * i if i % 3 == 0 else 5.0 for i in range(16))  # 5 m: no echo
    echo = tuple(i < 4 for i in range(16))
    with lab(wedge, p3dx) as it:
        sense = it.listen("/r1/sonar", "sensor_msgs/msg/PointCloud2")
        scan = it.listen("/r2/sonar", "sensor_msgs/msg/PointCloud2")
        time.sleep(0.3)
        still = {"x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0}
        it.send("sense", SenseFrame(robot_id="r1", tick=12, t_s=1.2, dt_s=0.1, v_mps=0.0,
                                    omega_radps=0.0, sonar_ranges_m=ranges, **still))  # fmt: skip
        it.send("scan", ScanMessage(robot_id="r2", stamp_s=1.3, ranges_m=(1.0,) * 16, echo=echo,
                                    **still))  # fmt: skip
        assert it.rounds_until(lambda: bool(sense.samples and scan.samples))
    cloud = sense.decoded("sensor_msgs/msg/PointCloud2")[0]
    assert (cloud.header.frame_id, cloud.header.stamp.nanosec) == ("r1/base_link", 200_000_000)
    assert [(f.name, f.offset, f.datatype) for f in cloud.fields] == [
        ("x", 0, 7), ("y", 4, 7), ("z", 8, 7)
    ]  # fmt: skip
    points = cloud.data.view("<f4").reshape(-1, 3)
    expected = [
        (u.x_m + r * math.cos(h), u.y_m + r * math.sin(h))
        for u, r in zip(p3dx.sonar.units, ranges, strict=True)
        if r < p3dx.sonar.max_range_m
        for h in [math.radians(u.heading_deg)]
    ]
    assert cloud.width == len(expected) == 6
    np.testing.assert_allclose(points[:, :2], expected, atol=1e-6)
    assert not points[:, 2].any()
    assert scan.decoded("sensor_msgs/msg/PointCloud2")[0].width == 4  # the echoes only


def test_markers_lay_the_slots_out_from_the_leader_and_draw_the_wall(
    wedge: Scenario, p3dx: RobotParams
) -> None:
    with lab(wedge, p3dx) as it:
        markers = it.listen("/markers", "visualization_msgs/msg/MarkerArray")
        time.sleep(0.3)
        it.send("state", state("r1", 1, x_m=3.0, y_m=1.0, theta_rad=math.pi / 2))
        assert it.rounds_until(lambda: bool(markers.samples))
    array = markers.decoded("visualization_msgs/msg/MarkerArray")[0]
    slots = {m.id: m for m in array.markers if m.ns == "slots"}
    # Facing +y, the wedge's slots 1 m behind-left and behind-right of the leader.
    assert (slots[0].pose.position.x, slots[0].pose.position.y) == pytest.approx((3.0, 1.0))
    behind = 1.0 - math.sqrt(0.5)
    assert (slots[1].pose.position.x, slots[1].pose.position.y) == pytest.approx(
        (3.0 - math.sqrt(0.5), behind)
    )
    assert (slots[2].pose.position.x, slots[2].pose.position.y) == pytest.approx(
        (3.0 + math.sqrt(0.5), behind)
    )
    (wall,) = [m for m in array.markers if m.ns == "walls"]
    assert wall.type == 4  # LINE_STRIP, closed
    assert len(wall.points) == len(wedge.world.polygons[0].vertices_m) + 1


def test_what_the_robots_send_is_checked_on_the_bridges_thread_and_the_newest_kept(
    wedge: Scenario, p3dx: RobotParams
) -> None:
    ring = RING_PER_ROBOT * len(wedge.robots)
    newest = 3 * ring + 1
    with lab(wedge, p3dx) as it:
        odom = it.listen("/r1/odom", "nav_msgs/msg/Odometry")
        time.sleep(0.3)

        def r1_heard() -> bool:  # (a key's first sample can be lost: sent until heard)
            it.send("state", state("r1", 1))
            return bool(odom.samples)

        assert it.rounds_until(r1_heard)
        stats, heard = it.hub.stats, it.bridge.stats.heard
        key = robot_key(FLEET, "r1", "state")
        # r1's key as the bridge's own session hears it: once a payload is here, it is in
        # the bridge's ring too, so a round is taken only once all are, however late. Each
        # is put with BLOCK: a robot's DROP may lose one of a burst on a busy machine, and
        # what is under test is what the bridge makes of those that arrive.
        arrived = Heard()
        listening = it.hub.zenoh.declare_subscriber(key, arrived.put)

        def put(payload: bytes) -> None:
            it.robots.zenoh.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

        def all_in(sent: list[bytes]) -> bool:
            return {payload for payload, _, _ in list(arrived.samples)}.issuperset(sent)

        garbage, wrong = b"{ not a state", encode(state("r2", 2))  # r2's state on r1's key
        put(garbage)
        put(wrong)
        assert wait_for(lambda: all_in([garbage, wrong]), WAIT_S)
        assert stats.malformed.total() + stats.rejected.total() == 0  # not decoded yet
        it.bridge.round()
        assert (stats.malformed["RobotState"], stats.rejected["RobotState"]) == (1, 1)
        before = heard["state"]
        states = [encode(state("r1", seq, x_m=0.01 * seq)) for seq in range(2, newest + 1)]
        for payload in states:  # three rings' worth before the next round
            put(payload)
        assert wait_for(lambda: all_in(states), WAIT_S)
        listening.undeclare()
        it.bridge.round()

        def last_x() -> float:
            return float(odom.decoded("nav_msgs/msg/Odometry")[-1].pose.pose.position.x)

        assert wait_for(lambda: last_x() == pytest.approx(0.01 * newest), WAIT_S)
    assert heard["state"] - before == ring  # the newest ring's worth, the rest dropped


def test_the_bridges_cdr_templates_write_what_rosbags_writes(p3dx: RobotParams) -> None:
    ours = RosMessages()
    r1 = RobotMessages(ours, "r1", map_frame="map", sonar=p3dx.sonar)
    rng = random.Random(48)
    for _ in range(300):
        t_s = rng.choice((rng.uniform(0.0, 600.0), rng.uniform(1.7e9, 1.8e9)))
        pose = Pose2D(rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(-4.0, 4.0))
        twist = Twist2D(rng.uniform(-1.0, 1.0), rng.uniform(-2.0, 2.0))
        cov = tuple(rng.uniform(-1.0, 1.0) for _ in range(6)) if rng.random() < 0.5 else ()
        ranges = tuple(rng.choice((rng.uniform(0.0, 5.0), 5.0)) for _ in p3dx.sonar.units)
        odom = ours.odometry(
            t_s, frame_id="map", child_frame_id="r1/base_link", pose=pose, twist=twist, cov=cov
        )
        cloud = ours.sonar_cloud(t_s, "r1/base_link", p3dx.sonar, ranges)
        for cdr, message, ros_type in (
            (r1.odometry_cdr(t_s, pose=pose, twist=twist, cov=cov), odom, "nav_msgs/msg/Odometry"),
            (r1.twist_cdr(twist), ours.twist(twist), "geometry_msgs/msg/Twist"),
            (r1.sonar_cdr(t_s, ranges), cloud, "sensor_msgs/msg/PointCloud2"),
        ):
            assert bytes(cdr) == bytes(ROSBAGS.serialize_cdr(message, ros_type))
    back = ROSBAGS.deserialize_cdr(bytes(r1.odometry_cdr(t_s, pose=pose, twist=twist, cov=cov)),
                                   "nav_msgs/msg/Odometry")  # fmt: skip
    assert (back.header.stamp.sec, back.pose.pose.position.x) == (int(t_s), pose.x_m)
    assert back.twist.twist.angular.z == twist.omega_radps
    points = ROSBAGS.deserialize_cdr(
        bytes(r1.sonar_cdr(t_s, ranges)), "sensor_msgs/msg/PointCloud2"
    )
    assert points.width == sum(r < p3dx.sonar.max_range_m for r in ranges)
    assert len(points.data) == 12 * points.width


def test_a_cdr_template_takes_numbers_in_one_place_and_a_byte_tail_with_nothing_after_it() -> None:
    odom = RosMessages().odometry(
        0.0, frame_id="map", child_frame_id="r1/base_link", pose=Pose2D(0.0, 0.0, 0.0),
        twist=Twist2D(0.0, 0.0),
    )  # fmt: skip
    with pytest.raises(ValueError, match="not a number"):
        CdrTemplate(odom, "nav_msgs/msg/Odometry", ["child_frame_id"])
    with pytest.raises(ValueError, match="no field 'seconds'"):
        CdrTemplate(odom, "nav_msgs/msg/Odometry", ["header.stamp.seconds"])
    value = message_class("rcl_interfaces/msg/ParameterValue")(
        type=0, bool_value=False, integer_value=0, double_value=0.0, string_value="",
        byte_array_value=np.zeros(0, np.uint8), bool_array_value=np.zeros(0, bool),
        integer_array_value=np.zeros(0, np.int64), double_array_value=np.zeros(0),
        string_array_value=[],
    )  # fmt: skip
    # int64s follow the bytes: where they start depends on how many bytes there are.
    with pytest.raises(ValueError, match="nothing after it"):
        CdrTemplate(value, "rcl_interfaces/msg/ParameterValue", [], tail="byte_array_value")
    numbers = CdrTemplate(
        value, "rcl_interfaces/msg/ParameterValue", ["integer_value", "double_value"]
    )
    back = ROSBAGS.deserialize_cdr(bytes(numbers((-7, 2.5))), "rcl_interfaces/msg/ParameterValue")
    assert (back.integer_value, back.double_value, back.string_value) == (-7, 2.5, "")


def test_the_node_and_its_publishers_are_in_the_ros_graph(
    wedge: Scenario, p3dx: RobotParams
) -> None:
    tokens: list[str] = []
    with lab(wedge, p3dx) as it:
        it.ros.liveliness().declare_subscriber(
            "@ros2_lv/0/**", lambda s: tokens.append(str(s.key_expr)), history=True
        )
        assert wait_for(lambda: len(tokens) >= 1 + len(it.bridge.topics), WAIT_S)
        zid = str(it.bridge.node_token.split("/")[2])
    parts = [t.split("/") for t in tokens]
    assert {p[2] for p in parts} == {zid}  # the bridge's session
    nodes = [p for p in parts if p[5] == "NN"]
    assert nodes == [["@ros2_lv", "0", zid, "0", "0", "NN", "%", "%", "phalanx_bridge"]]
    publishers = {p[9].replace("%", "/"): p for p in parts if p[5] == "MP"}
    assert set(publishers) == {t.name for t in it.bridge.topics}
    assert publishers["/r1/odom"][10:] == [
        "nav_msgs::msg::dds_::Odometry_",
        ROSBAGS.hash_rihs01("nav_msgs/msg/Odometry"),
        "::,10:,:,:,,",
    ]
    assert publishers["/tf_static"][12] == ":1:,1:,:,:,,"  # transient local, depth 1
    assert len({p[4] for p in publishers.values()}) == len(publishers)  # an id each


def test_a_late_subscriber_gets_the_sonar_mounts_from_the_cache(
    wedge: Scenario, p3dx: RobotParams
) -> None:
    from zenoh.ext import HistoryConfig, declare_advanced_subscriber

    heard = Heard()
    with lab(wedge, p3dx) as it:
        it.bridge.publish_static()
        time.sleep(0.3)  # published before anyone listened
        key = rmw_key("/tf_static", "tf2_msgs/msg/TFMessage")
        history = HistoryConfig(detect_late_publishers=True)
        declare_advanced_subscriber(it.ros, key, heard.put, history=history)
        assert wait_for(lambda: bool(heard.samples), WAIT_S)
    (message,) = heard.decoded("tf2_msgs/msg/TFMessage")
    links = {(t.header.frame_id, t.child_frame_id): t.transform for t in message.transforms}
    assert len(links) == 3 * len(p3dx.sonar.units)
    front = links["r2/base_link", "r2/sonar_3"]  # p3dx.toml: (0.166, 0.027) at 10 deg
    assert (front.translation.x, front.translation.y) == (0.166, 0.027)
    assert 2 * math.atan2(front.rotation.z, front.rotation.w) == pytest.approx(math.radians(10))


def test_an_independent_ros_2_client_lists_the_topics_and_decodes_odometry(
    wedge: Scenario, p3dx: RobotParams, sdk_registry: None
) -> None:
    from zenoh_ros2_sdk import ROS2Subscriber
    from zenoh_ros2_sdk.discovery import get_topic_info, get_topic_names_and_types

    got: list[Any] = []
    with lab(wedge, p3dx) as it:
        where = {"router_ip": "127.0.0.1", "router_port": it.port, "domain_id": 0}
        listed = dict(get_topic_names_and_types(timeout=1.0, **where))
        info = get_topic_info("/r1/odom", **where)
        teleop = get_topic_info("/cmd_vel", **where)
        sub = ROS2Subscriber("/r1/odom", "nav_msgs/msg/Odometry", got.append, **where)
        try:
            time.sleep(0.3)
            it.send("state", state("r1", 1, x_m=7.5))
            assert it.rounds_until(lambda: bool(got))
        finally:
            sub.close()
    assert listed == {t.name: [t.ros_type] for t in (*it.bridge.topics, *it.bridge.inputs)}
    assert (info.topic_types, info.publisher_count) == (["nav_msgs/msg/Odometry"], 1)
    assert (teleop.topic_types, teleop.subscriber_count) == (["geometry_msgs/msg/Twist"], 1)
    assert got[0].pose.pose.position.x == 7.5
    assert got[0].child_frame_id == "r1/base_link"
