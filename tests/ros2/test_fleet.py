"""A running fleet seen from ROS 2: the paper wedge as real processes (the world a Zenoh
router on loopback, three agents, real time), `phalanx ros2` started as a user would,
and a subscriber built only from ROBOTIS' zenoh-ros2-sdk (its keys, its type hash of
ROS's own definitions, its decoder) joining the world's router: it receives `/r1/odom`,
and each odometry it decodes is a state r1 published on phalanx's key, to the bit.

Then the bridge as part of a fleet: `phalanx up` of a scenario whose `[ros2]` is
enabled starts it beside the world and the agents (on the fleet's private socket), a
ROS 2 side (a router standing for rmw_zenoh's, a graph listing from the SDK, rosbags'
CDR) sees its topics and decodes the odometry, and the bridge ends with the fleet; and
a deployment whose `[ros2]` is enabled has its world's host daemon run it.
"""

from __future__ import annotations

import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from fleetlab import CLI, child_running, deployment_file, running_fleet, terminate, wait_for
from rosbags.typesys import Stores, get_typestore

from phalanx.wire.transport import FleetSession, TransportConfig, free_tcp_port, open_session

from .conftest import WEDGE

pytestmark = pytest.mark.integration
WAIT_S = 30.0
ODOMS = 20  # two seconds of r1's states at the bridge's 10 Hz


def test_an_independent_subscriber_sees_r1s_odometry_of_a_running_fleet(
    tmp_path: Path, sdk_registry: None
) -> None:
    from zenoh_ros2_sdk import ROS2Subscriber

    got: list[Any] = []
    lock = threading.Lock()

    def on_odom(message: Any) -> None:
        with lock:
            got.append(message)

    with running_fleet(tmp_path, fleet="rosfleet", duration_s=60.0) as fleet:
        port = int(fleet.endpoint.rsplit(":", 1)[1])
        argv = [sys.executable, "-m", "phalanx", "ros2", str(WEDGE), "--fleet", "rosfleet",
                "--mode", "client", "--connect", fleet.endpoint, "--duration", "45"]  # fmt: skip
        with (tmp_path / "ros2.log").open("wb") as log:
            bridge = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT)
        try:
            where = {"router_ip": "127.0.0.1", "router_port": port, "domain_id": 0}
            sub = ROS2Subscriber("/r1/odom", "nav_msgs/msg/Odometry", on_odom, **where)
            try:
                assert wait_for(lambda: len(got) >= ODOMS, WAIT_S), (
                    tmp_path / "ros2.log"
                ).read_text()
            finally:
                sub.close()
            states = {round(s.state.stamp_s, 6): s.state for s in fleet.watch.since("r1", 0.0)}
        finally:
            terminate([bridge], grace_s=5.0)
    assert bridge.returncode == 0, (tmp_path / "ros2.log").read_text()
    assert "Traceback" not in (tmp_path / "ros2.log").read_text()
    with lock:
        odoms = list(got)
    matched = 0
    for odom in odoms:
        assert (odom.header.frame_id, odom.child_frame_id) == ("map", "r1/base_link")
        stamp = round(odom.header.stamp.sec + odom.header.stamp.nanosec * 1e-9, 6)
        state = states.get(stamp)
        if state is not None:  # the watcher may have missed one; most it heard
            matched += 1
            position = odom.pose.pose.position
            assert (position.x, position.y) == (state.x_m, state.y_m)
            assert odom.twist.twist.linear.x == state.v_mps
    assert matched >= len(odoms) // 2


ODOM_TYPE = "nav_msgs/msg/Odometry"


@dataclass
class RosSide:
    """ROS 2's router on loopback (rmw_zenohd's place), with r1's odometry decoded by
    rosbags as it comes.
    """

    port: int
    session: FleetSession
    store: Any = field(default_factory=lambda: get_typestore(Stores.ROS2_JAZZY))
    got: list[Any] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_odom(self, sample: Any) -> None:
        """A sample of r1's odometry: decoded and kept."""
        message = self.store.deserialize_cdr(sample.payload.to_bytes(), ODOM_TYPE)
        with self.lock:
            self.got.append(message)

    def odoms(self) -> list[Any]:
        """The odometry decoded so far."""
        with self.lock:
            return list(self.got)

    def bridge_tokens(self) -> list[str]:
        """The liveliness tokens of a phalanx bridge left in the ROS graph."""
        tokens = self.session.zenoh.liveliness().get("@ros2_lv/0/**", timeout=2.0)
        keys = [str(r.ok.key_expr) for r in tokens if r.ok is not None]
        return [k for k in keys if "phalanx_bridge" in k]


@pytest.fixture
def ros_side() -> Iterator[RosSide]:
    """A ROS 2 side listening for r1's odometry."""
    port = free_tcp_port()
    with open_session(TransportConfig(mode="router", listen=(f"tcp/127.0.0.1:{port}",))) as ros:
        side = RosSide(port, ros)
        odom_key = f"0/r1/odom/nav_msgs::msg::dds_::Odometry_/{side.store.hash_rihs01(ODOM_TYPE)}"
        ros.zenoh.declare_subscriber(odom_key, side.on_odom)
        yield side


def test_phalanx_up_runs_the_bridge_with_the_fleet_and_stops_it_with_it(
    tmp_path: Path, sdk_registry: None, ros_side: RosSide
) -> None:
    from zenoh_ros2_sdk.discovery import get_topic_names_and_types

    port = ros_side.port
    ros_router = f'ros2.connect=["tcp/127.0.0.1:{port}"]'
    argv = [sys.executable, "-m", "phalanx", "up", str(WEDGE), "--fleet", "rosup", "--clock",
            "realtime", "--no-recording", "--timeout", "120", "--set", "duration_s=25",
            "--set", "ros2.enabled=true", "--set", ros_router]  # fmt: skip
    with (tmp_path / "up.log").open("wb") as log:
        up = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, cwd=tmp_path)
    try:
        assert wait_for(lambda: child_running(up.pid, "ros2") is not None, WAIT_S)
        bridge = child_running(up.pid, "ros2")
        got = ros_side.odoms
        assert wait_for(lambda: len(got()) >= ODOMS, WAIT_S), (tmp_path / "up.log").read_text()
        where = {"router_ip": "127.0.0.1", "router_port": port, "domain_id": 0}
        listed: dict[str, list[str]] = {}

        def graph_listed() -> bool:  # (a session just opened may not see all at once)
            listed.update(get_topic_names_and_types(timeout=1.0, **where))
            return {"/r1/odom", "/tf", "/cmd_vel"} <= set(listed)

        assert wait_for(graph_listed, WAIT_S, poll_s=0.5), listed
        code = up.wait(120)
    finally:
        terminate([up], grace_s=10.0)
    output = (tmp_path / "up.log").read_text()
    assert code == 0, output[-3000:]
    assert listed["/r1/odom"] == [ODOM_TYPE]
    assert listed["/tf"] == ["tf2_msgs/msg/TFMessage"]
    assert listed["/cmd_vel"] == ["geometry_msgs/msg/Twist"]  # (what it takes in)
    odoms = ros_side.odoms()
    assert {(o.header.frame_id, o.child_frame_id) for o in odoms} == {("map", "r1/base_link")}
    assert odoms[-1].pose.pose.position.x > odoms[0].pose.pose.position.x  # r1 drove on
    assert bridge is not None
    assert not Path(f"/proc/{bridge}").exists()  # stopped with the fleet
    assert not ros_side.bridge_tokens()  # and gone from the ROS graph


def test_a_deployments_host_daemon_runs_the_bridge_with_the_world(
    tmp_path: Path, ros_side: RosSide
) -> None:
    path, _ = deployment_file(tmp_path, name="rosdep", duration_s=15.0, recording=False)
    with path.open("a") as extra:
        extra.write(f'[ros2]\nenabled = true\nconnect = ["tcp/127.0.0.1:{ros_side.port}"]\n')
    argv = [*CLI, "launch", str(path), "--local", "--no-table", "--host-wait", "60"]
    with (tmp_path / "launch.log").open("wb") as log:
        launch = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, cwd=tmp_path)
    try:
        got = ros_side.odoms
        assert wait_for(lambda: len(got()) >= ODOMS, 90.0), (tmp_path / "launch.log").read_text()
        code = launch.wait(150)
    finally:
        terminate([launch], grace_s=20.0)
    output = (tmp_path / "launch.log").read_text()
    assert code == 0, output[-3000:]
    assert "[laptop/ros2-bridge] ros2: node @ros2_lv/0/" in output  # the world's host ran it
    assert {o.child_frame_id for o in ros_side.odoms()} == {"r1/base_link"}
    assert not ros_side.bridge_tokens()  # stopped with the run
