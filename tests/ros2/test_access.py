"""A secured deployment's access rules and its ROS 2 bridge: the bridge's identity
(`viewer.<[ros2] identity>`) may publish exactly the ROS keys the bridge uses and hold
exactly its tokens, and of phalanx's keys only the robots' `operator` (what ROS 2's
operator asks of the robot that leads); without an enabled `[ros2]` no rule names a
ROS key. First the rules as generated, held against every key and token a running
bridge declares (Zenoh's own key-expression matching); then a real router on loopback
`tls/` endpoints applying them: what the bridge may send arrives, what it may not does not.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest
import zenoh
from fleetlab import terminate, wait_for

from phalanx.core.config import Scenario
from phalanx.core.geometry import Twist2D
from phalanx.core.robot_params import RobotParams
from phalanx.hosts import pki
from phalanx.hosts.access import (
    bridge_keys,
    host_acl,
    identities,
    identity_files,
    operator_keys,
)
from phalanx.hosts.deployment import LoadedDeployment, load_deployment
from phalanx.hosts.wiring import local_endpoint, secured_host_transport
from phalanx.ros2.bridge import Bridge
from phalanx.ros2.messages import RosMessages
from phalanx.ros2.typestore import to_cdr
from phalanx.wire.keys import robot_key, robots_key
from phalanx.wire.messages import RobotState, SenseFrame
from phalanx.wire.transport import (
    FleetSession,
    TransportConfig,
    free_tcp_port,
    open_session,
    zenoh_config,
)

from .conftest import WEDGE

WAIT_S = 10.0


def _deployment(folder: Path, ros2: str) -> Path:
    text = f"""name = "sec"
fleet = "sec"
scenario = "{WEDGE}"
[security]
mode = "mtls"
viewers = ["bob"]
[[hosts]]
name = "laptop"
address = "127.0.0.1"
port = {free_tcp_port()}
[[hosts]]
name = "robot-a"
address = "127.0.0.2"
port = {free_tcp_port()}
[world]
host = "laptop"
[[robots]]
id = "r1"
host = "robot-a"
[[robots]]
id = "r2"
host = "robot-a"
[[robots]]
id = "r3"
host = "laptop"
{ros2}
"""
    path = folder / "sec.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def secured(tmp_path_factory: pytest.TempPathFactory) -> LoadedDeployment:
    """The deployment with `[ros2]` on, every identity issued."""
    folder = tmp_path_factory.mktemp("sec")
    loaded = load_deployment(_deployment(folder, '[ros2]\nenabled = true\nnamespace = "lab"'))
    pki.init_ca(folder / "pki", fleet="sec")
    for ident in identities(loaded.spec):
        pki.issue(folder / "pki", ident.common_name, addresses=ident.addresses)
    return loaded


def _rules(acl: Any) -> dict[str, dict[str, Any]]:
    return {r["id"]: r for r in acl.zenoh_json()["rules"]}


def _state(rid: str, seq: int = 1, leader: str = "") -> RobotState:
    still = {"x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0, "v_mps": 0.0, "omega_radps": 0.0}
    return RobotState(
        robot_id=rid, seq=seq, stamp_s=0.1 * seq, fsm_state="HOLD", formation_leader_id=leader,
        **still,
    )  # fmt: skip


def _twist_cdr(v_mps: float) -> bytes:
    """A geometry_msgs/Twist as a ROS 2 node sends it on cmd_vel."""
    return to_cdr(RosMessages().twist(Twist2D(v_mps, 0.0)), "geometry_msgs/msg/Twist")


def _frame(rid: str) -> SenseFrame:
    still = {"x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0, "v_mps": 0.0, "omega_radps": 0.0}
    return SenseFrame(robot_id=rid, tick=1, t_s=0.1, dt_s=0.1, sonar_ranges_m=(1.0,) * 16, **still)


def _declared(wedge: Scenario, p3dx: RobotParams, loaded: LoadedDeployment) -> list[str]:
    """Every key and token a bridge of this deployment declares and sends, as seen by
    another session: data keys, graph tokens, its cache's own keys, and (asked by ROS 2's
    operator, each robot leading in turn) every robot's operator key.
    """
    assert loaded.spec.ros2 is not None
    cfg = loaded.spec.ros2
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    seen: set[str] = set()
    lock = threading.Lock()

    def note(sample: Any) -> None:
        with lock:
            seen.add(str(sample.key_expr))

    with ExitStack() as stack:
        hub = stack.enter_context(open_session(TransportConfig(listen=(endpoint,))))
        robots = stack.enter_context(open_session(TransportConfig(connect=(endpoint,))))
        ros = zenoh.open(zenoh_config(TransportConfig(connect=(endpoint,))))
        stack.callback(ros.close)
        ros.declare_subscriber(f"{cfg.domain_id}/**", note)
        ros.declare_subscriber(robots_key("sec", "operator"), note)
        ros.liveliness().declare_subscriber(f"@ros2_lv/{cfg.domain_id}/**", note, history=True)
        tf_static = next(k for k in bridge_keys(loaded.spec).puts if "/tf_static/" in k)  # type: ignore[union-attr]
        ros.liveliness().declare_subscriber(f"{tf_static}/@adv/**", note, history=True)
        bridge = Bridge(hub, fleet="sec", scenario=loaded.scenario, robot=p3dx, cfg=cfg)
        time.sleep(0.3)
        bridge.publish_static()
        for rid in ("r1", "r2", "r3"):  # a state and a sonar ring each: every topic has news
            robots.publish(robot_key("sec", rid, "state"), _state(rid))
            robots.publish(robot_key("sec", rid, "sense"), _frame(rid))
        cmd_vel = next(s.key for s in bridge.subscriptions() if s.topic.kind == "cmd_vel")
        for seq, rid in enumerate(("r1", "r2", "r3"), start=2):  # each leads in turn

            def driven(rid: str = rid) -> bool:
                robots.zenoh.put(cmd_vel, _twist_cdr(0.1))
                bridge.round()
                with lock:
                    return robot_key("sec", rid, "operator") in seen

            robots.publish(robot_key("sec", rid, "state"), _state(rid, seq, leader=rid))
            assert wait_for(driven, WAIT_S, poll_s=0.05)

        # every topic's key and token, the node's, the cache's, the subscriptions' tokens
        wanted = 2 * len(bridge.topics) + len(bridge.inputs) + 2 + 3

        def everything() -> bool:
            for rid in ("r1", "r2", "r3"):  # a key's first sample can be lost: sent again
                robots.publish(robot_key("sec", rid, "sense"), _frame(rid))
            bridge.round()
            with lock:
                return len(seen - {cmd_vel}) >= wanted

        assert wait_for(everything, WAIT_S, poll_s=0.05)
    return sorted(seen - {cmd_vel})  # (what ROS 2 sent the bridge is not the bridge's)


def test_the_bridge_may_send_exactly_its_keys(
    secured: LoadedDeployment, wedge: Scenario, p3dx: RobotParams
) -> None:
    acl = host_acl(secured.spec, "laptop")
    rules = _rules(acl)
    policies = {p["id"]: p for p in acl.zenoh_json()["policies"]}
    subjects = {s["id"]: s["cert_common_names"] for s in acl.zenoh_json()["subjects"]}
    assert subjects["s-ros2"] == ["viewer.ros2"]
    originate = [rules[r] for r in policies["ros2"]["rules"] if r.startswith("ros2-")]
    allowed = [zenoh.KeyExpr(k) for rule in originate for k in rule["key_exprs"]]
    sent = _declared(wedge, p3dx, secured)
    for key in sent:  # everything the bridge sends is allowed
        assert any(pattern.includes(zenoh.KeyExpr(key)) for pattern in allowed), key
    for pattern in allowed:  # and every rule is used by something the bridge sends
        assert any(pattern.includes(zenoh.KeyExpr(key)) for key in sent), pattern
    puts = rules["ros2-put"]["key_exprs"]
    assert all("*" not in k for k in puts)  # data keys exactly, no wildcard
    assert sorted(puts) == sorted(k for k in sent if not k.startswith("@") and "/@adv/" not in k)
    fleet_keys = [k for rule in originate for k in rule["key_exprs"] if k.startswith("phalanx/")]
    assert fleet_keys == operator_keys(secured.spec)  # of phalanx's, the operator's alone
    assert fleet_keys == [f"phalanx/sec/robot/{r}/operator" for r in ("r1", "r2", "r3")]
    assert rules["ros2-put"]["messages"] == ["put"]


def test_the_other_hosts_carry_the_bridges_keys_from_its_host_only(
    secured: LoadedDeployment,
) -> None:
    robot_a = _rules(host_acl(secured.spec, "robot-a"))
    keys = bridge_keys(secured.spec)
    assert keys is not None
    carried = [*keys.puts, *operator_keys(secured.spec)]
    assert robot_a["host.laptop-ros2-put"]["key_exprs"] == carried
    assert "ros2-put" not in robot_a  # the bridge joins the laptop's router
    laptop = _rules(host_acl(secured.spec, "laptop"))
    assert not any(r.startswith("host.robot-a-ros2") for r in laptop)


def test_without_ros2_no_rule_names_a_ros_key(tmp_path: Path) -> None:
    for section in ("", "[ros2]\nenabled = false"):
        spec = load_deployment(_deployment(tmp_path, section)).spec
        assert bridge_keys(spec) is None
        assert operator_keys(spec) == []
        assert "viewer.ros2" not in {i.common_name for i in identities(spec)}
        for host in ("laptop", "robot-a"):
            text = str(host_acl(spec, host).zenoh_json())
            assert "@ros2_lv" not in text
            assert "dds_" not in text
            assert "/operator" not in text
    # a bridge that takes nothing from ROS 2 may publish on no key of the fleet
    spec = load_deployment(_deployment(tmp_path, "[ros2]\nenabled = true\ninputs = []")).spec
    assert operator_keys(spec) == []
    assert "/operator" not in str(host_acl(spec, "laptop").zenoh_json())


def _client(loaded: LoadedDeployment, identity: str) -> FleetSession:
    endpoint = local_endpoint(loaded.spec, "laptop")
    files = identity_files(loaded, identity)
    return FleetSession(
        TransportConfig(mode="client", connect=(endpoint,), tls=files, open_timeout_s=5.0)
    )


@pytest.fixture
def router(secured: LoadedDeployment) -> Iterator[FleetSession]:
    """The laptop's router: its tls/ endpoint and its access-control list."""
    with FleetSession(secured_host_transport(secured, "laptop")) as session:
        yield session


@pytest.mark.integration
def test_a_router_applying_the_rules_passes_the_bridges_keys_and_no_other(
    secured: LoadedDeployment, p3dx: RobotParams, router: FleetSession
) -> None:
    # What comes into the router is seen by a subscriber of its own (its links' ingress
    # is where the rules apply); a viewer, a client like any ROS tool, reads the odometry.
    assert secured.spec.ros2 is not None
    keys = bridge_keys(secured.spec)
    assert keys is not None
    odom = next(k for k in keys.puts if "/lab/r3/odom/" in k)
    forged = odom.replace("/r3/odom/", "/r3/cmd_vel/")  # what a ROS tool would drive r3 with
    inside, viewer = Heard(), Heard()
    router.zenoh.declare_subscriber("0/**", inside.note)
    router.zenoh.declare_subscriber("phalanx/sec/**", inside.note)
    with ExitStack() as stack:
        bob = stack.enter_context(_client(secured, "viewer.bob"))
        bob.zenoh.declare_subscriber(odom, viewer.note)
        ros = stack.enter_context(_client(secured, "viewer.ros2"))
        r3 = stack.enter_context(_client(secured, "robot.r3"))
        bridge = Bridge(
            ros, fleet="sec", scenario=secured.scenario, robot=p3dx, cfg=secured.spec.ros2
        )
        time.sleep(0.5)
        r3.publish(robot_key("sec", "r3", "state"), _state("r3"))

        def odom_heard() -> bool:
            bridge.round()
            return bool(viewer.of(odom))

        assert wait_for(odom_heard, WAIT_S, poll_s=0.05)  # the bridge's own: it arrives
        operated = robot_key("sec", "r1", "operator")
        ros.publish_raw(operated, OPERATED)  # the bridge's one key of the fleet's
        ros.publish_raw(forged, FORGED)  # a ROS key not the bridge's
        ros.publish_raw(robot_key("sec", "r1", "state"), FORGED)  # a phalanx key
        ros.publish_raw(robot_key("sec", "r1", "cmd"), FORGED)  # a robot's wheels
        r3.publish_raw(odom, FORGED)  # a robot speaking ROS for the bridge
        r3.publish_raw(operated, FORGED)  # a robot speaking for the operator
        r3.publish(robot_key("sec", "r3", "state"), _state("r3", seq=2))  # the last one sent
        assert wait_for(lambda: len(inside.of(robot_key("sec", "r3", "state"))) >= 2, WAIT_S)
        time.sleep(0.3)
    assert inside.of(odom)
    assert inside.of(operated) == [OPERATED]
    assert not inside.of(forged)
    assert not inside.of(robot_key("sec", "r1", "state"))
    assert not inside.of(robot_key("sec", "r1", "cmd"))
    assert FORGED not in inside.of(odom) + viewer.of(odom)


FORGED = b"\x00\x01\x00\x00forged"
OPERATED = b"\x0d\x01operated"


class Heard:
    """Payloads by key, as they arrive (a Zenoh callback)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._by_key: dict[str, list[bytes]] = {}

    def note(self, sample: Any) -> None:
        with self._lock:
            self._by_key.setdefault(str(sample.key_expr), []).append(sample.payload.to_bytes())

    def of(self, key: str) -> list[bytes]:
        with self._lock:
            return list(self._by_key.get(key, []))


@pytest.mark.integration
def test_phalanx_ros2_joins_a_deployments_router_as_the_bridges_identity(
    secured: LoadedDeployment, router: FleetSession, tmp_path: Path
) -> None:
    keys = bridge_keys(secured.spec)
    assert keys is not None
    odom = next(k for k in keys.puts if "/lab/r3/odom/" in k)
    inside = Heard()
    router.zenoh.declare_subscriber(odom, inside.note)
    argv = [sys.executable, "-m", "phalanx", "ros2", "--deployment", str(secured.path),
            "--duration", "20"]  # fmt: skip
    log = tmp_path / "ros2.log"
    with log.open("wb") as out, _client(secured, "robot.r3") as r3:
        bridge = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT)
        try:

            def odom_heard() -> bool:
                r3.publish(robot_key("sec", "r3", "state"), _state("r3", seq=next(seqs)))
                return bool(inside.of(odom))

            seqs = iter(range(1, 10_000))
            assert wait_for(odom_heard, WAIT_S, poll_s=0.1), log.read_text()
        finally:
            terminate([bridge], grace_s=5.0)
    assert bridge.returncode == 0, log.read_text()
