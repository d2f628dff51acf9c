"""A running fleet seen from ROS 2: the paper wedge as real processes (the world a Zenoh
router on loopback, three agents, real time), `phalanx ros2` started as a user would,
and a subscriber built only from ROBOTIS' zenoh-ros2-sdk (its keys, its type hash of
ROS's own definitions, its decoder) joining the world's router: it receives `/r1/odom`,
and each odometry it decodes is a state r1 published on phalanx's key, to the bit.
"""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
from fleetlab import running_fleet, terminate, wait_for

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
