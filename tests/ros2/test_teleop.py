"""ROS 2 drives the leader: `cmd_vel` and `goal_pose` sent by publishers built only from
ROBOTIS' zenoh-ros2-sdk (its keys, its type hashes of ROS's own definitions, its CDR and
attachment), taken by the bridge with rmw_zenoh's subscription tokens and passed to the
robot that leads as one operator command on phalanx's key.

First the bridge alone on real Zenoh sessions: what reaches which robot, clamped to the
robot's rating, and what is refused. Then a running fleet (the world a Zenoh router on
loopback, three agents, real time, the emergency stop on, a post ahead of the leader)
with `phalanx ros2` started as a user would: the leader drives as the operator asks,
within its limits, the followers keep the wedge, the leader goes back to its script
once the commands stop, and the emergency stop outranks the operator.
"""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from fleetlab import running_fleet, terminate, wait_for

from phalanx.core.config import Ros2Config, Scenario
from phalanx.core.config_files import load_robot
from phalanx.core.robot_params import RobotParams
from phalanx.wire.keys import robot_key, robots_key
from phalanx.wire.messages import OperatorCommand

from .conftest import WEDGE
from .test_bridge import FLEET, WAIT_S, lab, state


class RosOperator:
    """ROS 2's side: a teleop node's `/cmd_vel` and RViz's `/goal_pose` publishers, from
    the SDK alone, joined to the router on `port`.
    """

    def __init__(self, port: int) -> None:
        from zenoh_ros2_sdk import ROS2Publisher

        where = {"router_ip": "127.0.0.1", "router_port": port, "domain_id": 0}
        self.cmd_vel = ROS2Publisher("/cmd_vel", "geometry_msgs/msg/Twist", **where)
        self.goal_pose = ROS2Publisher("/goal_pose", "geometry_msgs/msg/PoseStamped", **where)
        self.types = self.cmd_vel.session_mgr.store.types
        self.sent_at = 0.0  # when the last twist went (monotonic)

    def twist(self, v_mps: float, omega_radps: float) -> None:
        vector = self.types["geometry_msgs/msg/Vector3"]
        self.cmd_vel.publish(
            linear=vector(x=v_mps, y=0.0, z=0.0), angular=vector(x=0.0, y=0.0, z=omega_radps)
        )
        self.sent_at = time.monotonic()

    def goal(self, x_m: float, y_m: float, frame: str = "map") -> None:
        t = self.types
        header = t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id=frame
        )
        pose = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=x_m, y=y_m, z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        )
        self.goal_pose.publish(header=header, pose=pose)

    def close(self) -> None:
        self.cmd_vel.close()
        self.goal_pose.close()


class Commands:
    """Operator commands as the robots' side hears them: (key, command)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.got: list[tuple[str, OperatorCommand]] = []

    def on(self, key: str, command: OperatorCommand) -> None:
        with self.lock:
            self.got.append((key, command))

    def all(self) -> list[tuple[str, OperatorCommand]]:
        with self.lock:
            return list(self.got)


@contextmanager
def operated(wedge: Scenario, p3dx: RobotParams) -> Iterator[tuple[Any, RosOperator, Commands]]:
    """The bridge on real sessions (`lab`), the robots' side hearing operator commands,
    and a ROS 2 operator on the bridge's router.
    """
    heard = Commands()
    with lab(wedge, p3dx) as it:
        it.robots.subscribe(robots_key(FLEET, "operator"), OperatorCommand, heard.on)
        operator = RosOperator(it.port)
        try:
            yield it, operator, heard
        finally:
            operator.close()


def test_cmd_vel_and_goal_pose_go_to_the_robot_that_leads(
    wedge: Scenario, p3dx: RobotParams, sdk_registry: None
) -> None:
    with operated(wedge, p3dx) as (it, operator, heard):
        it.send("state", state("r1", 1, formation_leader_id="r2"))  # r2 leads
        assert it.rounds_until(lambda: it.bridge.stats.heard["state"] > 0)
        time.sleep(0.5)  # (the SDK's publishers and the bridge's subscriptions meet)
        operator.twist(0.2, -0.3)
        operator.goal(4.0, -2.5)
        assert it.rounds_until(lambda: bool(heard.all()))
        assert it.rounds_until(lambda: any(c.goal for _, c in heard.all()))
        operator.twist(5.0, 9.0)  # beyond the robot's rating
        assert it.rounds_until(lambda: len([c for _, c in heard.all() if c.twist]) >= 2)
    got = heard.all()
    assert {key for key, _ in got} == {robot_key(FLEET, "r2", "operator")}
    twists = [c for _, c in got if c.twist]
    assert (twists[0].v_mps, twists[0].omega_radps) == (0.2, -0.3)
    goal = next(c for _, c in got if c.goal)
    assert (goal.goal_x_m, goal.goal_y_m) == (4.0, -2.5)
    assert (twists[-1].v_mps, twists[-1].omega_radps) == (p3dx.v_max_mps, p3dx.omega_max_radps)
    assert all(c.robot_id == "r2" for _, c in got)
    assert it.bridge.stats.refused.total() == 0


def test_what_the_bridge_refuses_of_ros_2_is_counted_and_never_sent(
    wedge: Scenario, p3dx: RobotParams, sdk_registry: None
) -> None:
    with operated(wedge, p3dx) as (it, operator, heard):
        cmd_vel = next(s.key for s in it.bridge.subscriptions() if s.topic.kind == "cmd_vel")
        time.sleep(0.5)
        operator.twist(0.1, 0.0)  # nobody has been heard leading yet
        assert it.rounds_until(lambda: it.bridge.stats.refused["operator"] > 0)
        it.send("state", state("r1", 1))
        operator.goal(1.0, 1.0, frame="odom")  # a goal in another frame
        operator.twist(math.nan, 0.0)
        it.ros.put(cmd_vel, b"\x00\x01\x00\x00\xff")  # no Twist
        assert it.rounds_until(lambda: it.bridge.stats.refused.total() >= 4)
        time.sleep(0.3)
        it.bridge.round()
    assert heard.all() == []
    refused = it.bridge.stats.refused
    assert (refused["operator"], refused["goal_pose"], refused["cmd_vel"]) == (1, 1, 2)


def test_a_bridge_that_takes_nothing_from_ros_2_subscribes_to_nothing(
    wedge: Scenario, p3dx: RobotParams
) -> None:
    with lab(wedge, p3dx, Ros2Config(inputs=())) as it:
        assert it.bridge.subscriptions() == []
        assert it.bridge.inputs == []


# --- a running fleet ----------------------------------------------------------------------

# A post on the leader's way, the followers passing it by: far enough that the script
# (0.15 m/s from x = 0) is still 4 m short of it 25 s into the run, when a loaded machine
# may only just have the bridge up (at 5 m it would be within its braking distance by
# 29 s): phase 1 must see the operator drive, not the emergency stop. (A CI run under
# load once saw no TELEOP at all in phase 1, the post at 5 m; its states were not kept.)
POST_X_M, POST_R_M = 8.0, 0.2


class Stick:
    """An operator's hand on the stick: the twist it holds, sent at 10 Hz from a thread
    of its own (None: let go, nothing sent).
    """

    def __init__(self, operator: RosOperator) -> None:
        self.operator = operator
        self.held: tuple[float, float] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.wait(0.1):
            held = self.held
            if held is not None:
                self.operator.twist(*held)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


@pytest.mark.integration
def test_a_fleets_leader_driven_from_ros_2(tmp_path: Path, sdk_registry: None) -> None:
    scenario = tmp_path / "wedge_post.toml"
    scenario.write_text(
        WEDGE.read_text()
        + f"\n[[world.circles]]\nx_m = {POST_X_M}\ny_m = 0.0\nradius_m = {POST_R_M}\n"
    )
    sets = ("navigation.reactive=true",)
    with running_fleet(
        tmp_path, fleet="teleop", duration_s=150.0, scenario=scenario, sets=sets
    ) as fleet:
        argv = [sys.executable, "-m", "phalanx", "ros2", str(scenario), "--fleet", "teleop",
                "--mode", "client", "--connect", fleet.endpoint, "--duration", "140",
                "--set", sets[0]]  # fmt: skip
        with (tmp_path / "ros2.log").open("wb") as log:
            bridge = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT)
        operator = RosOperator(int(fleet.endpoint.rsplit(":", 1)[1]))
        stick = Stick(operator)
        try:
            assert fleet.wait_tracking(60.0), fleet.tracebacks()
            _drive(fleet, stick)
        finally:
            stick.close()
            operator.close()
            terminate([bridge], grace_s=5.0)
        assert fleet.crashed() == [], fleet.tracebacks()
    assert bridge.returncode == 0, (tmp_path / "ros2.log").read_text()


def _drive(fleet: Any, stick: Stick) -> None:
    """The operator's session, phase by phase, each held to what the leader must do."""
    watch = fleet.watch
    # 1. Within the limits: the leader drives as asked, the followers keep the wedge.
    began = time.monotonic()
    stick.held = (0.1, 0.1)
    assert wait_for(lambda: _latest_state(watch, "r1") == "TELEOP", WAIT_S)
    time.sleep(3.0)
    stick.held = (0.1, -0.1)
    time.sleep(3.0)
    driven = [s.state for s in watch.since("r1", began + 2.0)]
    # (a stick or a bridge starved for half a second on a loaded machine lets go: rarely)
    seen = [(s.fsm_state, round(s.stamp_s, 1), round(s.x_m, 2)) for s in driven[-20:]]
    assert sum(s.fsm_state == "TELEOP" for s in driven[-20:]) >= 18, seen
    steady = [s for s in driven[-10:] if s.omega_radps < 0.0]
    assert steady, [(s.v_mps, s.omega_radps) for s in driven[-20:]]
    for s in steady[-5:]:
        assert (s.v_mps, s.omega_radps) == pytest.approx((0.1, -0.1), abs=0.011)
    for rid in ("r2", "r3"):
        follower = watch.latest(rid).state
        assert follower.fsm_state == "FORMATION_TRACK"
        lead = driven[-1]
        gap_m = math.hypot(follower.x_m - lead.x_m, follower.y_m - lead.y_m)
        assert gap_m == pytest.approx(1.0, abs=0.25)
    # 2. Beyond the limits: held to them (the shape's share of the run's 0.3 m/s).
    mark = time.monotonic()
    stick.held = (2.0, 0.0)
    time.sleep(3.0)
    fast = [s.state for s in watch.since("r1", mark)]
    assert max(s.v_mps for s in fast) == pytest.approx(0.27, abs=0.011)
    assert all(abs(s.v_mps) <= 0.3 + 1e-9 for s in fast)
    assert sum(s.fsm_state == "TELEOP" for s in fast[5:]) >= len(fast[5:]) - 2
    # 3. Let go: back to the script within half a second of the operator's last word
    # (and the state's trip to this watcher, on a loaded machine).
    stick.held = None
    assert wait_for(lambda: _latest_state(watch, "r1") == "NAVIGATE", WAIT_S)
    last_word = stick.operator.sent_at
    back = next(s for s in watch.since("r1", last_word) if s.state.fsm_state == "NAVIGATE")
    assert back.at - last_word < 0.5 + 1.0
    before = [s.state for s in watch.since("r1", last_word) if s.at < back.at]
    assert all(s.fsm_state == "TELEOP" for s in before)
    assert len(before) <= 10  # about 0.5 s of steps, give or take the step it was heard at
    # 4. At the post: the emergency stop outranks the operator, who keeps asking.
    stick.held = (0.3, 0.0)
    assert wait_for(lambda: _latest_state(watch, "r1") == "EMERGENCY_STOP", 60.0)
    stopped = time.monotonic()
    time.sleep(3.0)
    held = [s.state for s in watch.since("r1", stopped + 1.0)]
    assert held
    assert {s.fsm_state for s in held} == {"EMERGENCY_STOP"}
    assert all(s.v_mps == 0.0 for s in held)
    nearest_m = min(math.hypot(s.state.x_m - POST_X_M, s.state.y_m) for s in watch.since("r1", 0))
    assert nearest_m > POST_R_M + load_robot("p3dx").radius_m  # short of it


def _latest_state(watch: Any, rid: str) -> str:
    seen = watch.latest(rid)
    return "" if seen is None else str(seen.state.fsm_state)
