"""The bridge behind `phalanx ros2`: a fleet's robots as ROS 2 topics over rmw_zenoh.

It joins the fleet's Zenoh fabric and only reads phalanx's keys: every robot's `state`
(pose, the twist it drives, its behaviour state, who leads), and for the sonar its
`scan` (a navigating robot's echoes) and `sense` frames (a simulated robot's ring). What
arrives waits in Zenoh's own bounded rings (`_Inbox`: no Python runs on Zenoh's
threads); `rate_hz` times a second a round decodes it, takes the newest of each robot
and publishes in rmw_zenoh's key space (`phalanx.ros2.topics`): odometry, the command,
TF, the behaviour state (when it changes, and once a second), the sonar ring, and once
a second the formation's slots (laid out from the formation leader's pose) with the
world's obstacles. `/tf_static` (every robot's sonar mounts) goes out once, from a cache
late subscribers query. Each robot's messages are built once and refilled every round
(`RobotMessages`), and each type's CDR serialiser is looked up once (`CdrWriter`).

The other way, it subscribes to `cmd_vel` and `goal_pose` in the fleet's namespace
(`[ros2] inputs`) with rmw_zenoh's subscription tokens: each round, the newest twist
(clamped to the robot's rating) and the newest goal (in the map frame) that came since
the last go to the robot that leads, as one `OperatorCommand` on its `operator` key,
the only phalanx key the bridge publishes on. The robot's behaviour stack decides what
to do with it (`phalanx.agents`: TELEOP, within its limits, the emergency stop first).

The fleet's keys are read (and the operator's commands sent) on `session`; the ROS 2
side can have a session of its own (`ros`: joined to ROS 2's router), else it is the
same one.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from pydantic import ValidationError

from phalanx.core.config import Ros2Config, Scenario
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import Pose2D, Twist2D, Vec2
from phalanx.core.quantities import MAX_EXTENT_M
from phalanx.core.robot_params import RobotParams
from phalanx.core.scenarios import resolve_world
from phalanx.ros2.graph import RosNode, RosPublisher, RosSubscription
from phalanx.ros2.messages import (
    FleetMarkers,
    RobotMessages,
    RosMessages,
    planar_twist,
    sonar_mounts,
    stamped_position,
)
from phalanx.ros2.names import fleet_namespace
from phalanx.ros2.topics import fleet_inputs, fleet_topics
from phalanx.ros2.typestore import CdrWriter, cdr_writer, from_cdr
from phalanx.wire.bounds import FleetBounds
from phalanx.wire.delivery import deliver
from phalanx.wire.keys import robot_key, robots_key
from phalanx.wire.messages import Message, OperatorCommand, RobotState, ScanMessage, SenseFrame
from phalanx.wire.transport import FleetSession

SLOW_PERIOD_S = 1.0  # the behaviour state's heartbeat and the markers' period
RING_PER_ROBOT = 8  # messages of one kind a robot may have waiting between two rounds
M = TypeVar("M", bound=Message)


@dataclass
class BridgeStats:
    """What the bridge did: rounds, messages in (by phalanx key, and by ROS topic kind
    for what ROS 2 sent), out (by ROS topic kind, and `operator`), what it refused of
    ROS 2's (by topic kind: undecodable, not finite, a goal in another frame or with
    nobody leading) with the last reason, and the CPU time its rounds took.
    """

    rounds: int = 0
    heard: Counter[str] = field(default_factory=Counter)
    sent: Counter[str] = field(default_factory=Counter)
    refused: Counter[str] = field(default_factory=Counter)
    last_refusal: str = ""
    cpu_s: float = 0.0


@dataclass
class _Robot:
    """What the bridge holds of one robot between rounds."""

    messages: RobotMessages
    state: RobotState | None = None
    fresh: bool = False
    said: str = ""  # the behaviour state last published
    said_at: float = -math.inf  # when (monotonic s)
    ranges: tuple[float, ...] = ()
    ranges_stamp_s: float = -1.0
    ranges_fresh: bool = False


class Bridge:
    """One fleet's robots published to ROS 2 on `session` (which it does not close)."""

    def __init__(
        self, session: FleetSession, *, fleet: str, scenario: Scenario, robot: RobotParams,
        cfg: Ros2Config, ros: FleetSession | None = None,
    ) -> None:  # fmt: skip
        self.cfg, self.scenario, self.robot = cfg, scenario, robot
        self.stats = BridgeStats()
        ids = [r.id for r in scenario.robots]
        self.topics = fleet_topics(cfg, ids)
        self.inputs = fleet_inputs(cfg)
        self._msgs = RosMessages(cfg.distro)
        self._robots = {
            rid: _Robot(RobotMessages(self._msgs, rid, map_frame=cfg.map_frame, sonar=robot.sonar))
            for rid in ids
        }
        self._formation = scenario_formation(scenario)
        self._markers = FleetMarkers(
            self._msgs, cfg.map_frame, slots=len(self._formation.positions),
            radius_m=robot.radius_m, world=resolve_world(scenario.world),
        )  # fmt: skip
        self._tf = self._msgs.transforms(0.0, [])
        self._session, self._fleet = session, fleet
        node = RosNode(
            ros or session, domain_id=cfg.domain_id, namespace=fleet_namespace(cfg), name=cfg.node
        )
        self._pubs: dict[tuple[str, str], RosPublisher] = {
            (t.kind, t.robot_id): node.publisher(t) for t in self.topics
        }
        self._cdr: dict[str, CdrWriter] = {
            t.ros_type: cdr_writer(t.ros_type, cfg.distro) for t in self.topics
        }
        self._subs: dict[str, RosSubscription] = {t.kind: node.subscription(t) for t in self.inputs}
        self.node_token = node.token
        self._markers_at = -math.inf
        bounds = FleetBounds.of(scenario, robot)
        ring = RING_PER_ROBOT * len(ids)

        def inbox(kind: str, model: type[M]) -> _Inbox[M]:
            return _Inbox(session, robots_key(fleet, kind), model, ring, context=bounds)

        self._rings: list[tuple[str, _Inbox[Any], Callable[[str, Any], None]]] = [
            ("state", inbox("state", RobotState), self._on_state)
        ]
        if "sonar" in cfg.topics:
            self._rings += [
                ("scan", inbox("scan", ScanMessage), self._on_scan),
                ("sense", inbox("sense", SenseFrame), self._on_sense),
            ]

    def publishers(self) -> list[RosPublisher]:
        """Every ROS publisher of the bridge."""
        return list(self._pubs.values())

    def subscriptions(self) -> list[RosSubscription]:
        """Every ROS subscription of the bridge."""
        return list(self._subs.values())

    def _send(self, kind: str, robot_id: str, message: Any) -> None:
        publisher = self._pubs.get((kind, robot_id))
        if publisher is not None:
            self._send_cdr(publisher, self._cdr[publisher.topic.ros_type](message))

    def _send_cdr(self, publisher: RosPublisher, payload: bytes | bytearray) -> None:
        publisher.put(payload)
        self.stats.sent[publisher.topic.kind] += 1

    def _wanted(self, kind: str, robot_id: str = "") -> bool:
        return (kind, robot_id) in self._pubs

    def publish_static(self, t_s: float = 0.0) -> None:
        """Every robot's sonar mounts on `/tf_static` (stamped `t_s`)."""
        if self._wanted("tf_static"):
            links = sonar_mounts(self._robots, self.robot.sonar)
            self._send("tf_static", "", self._msgs.transforms(t_s, links))

    # --- what arrives ---------------------------------------------------------------------

    def _take(self) -> None:
        for name, ring, handler in self._rings:
            self.stats.heard[name] += ring.drain(handler)

    def _on_state(self, _key: str, state: RobotState) -> None:
        held = self._robots[state.robot_id]
        if held.state is None or state.stamp_s >= held.state.stamp_s:
            held.state, held.fresh = state, True

    def _ring(self, robot_id: str, stamp_s: float, ranges: tuple[float, ...]) -> None:
        held = self._robots[robot_id]
        if stamp_s >= held.ranges_stamp_s:
            held.ranges, held.ranges_stamp_s, held.ranges_fresh = ranges, stamp_s, True

    def _on_scan(self, _key: str, scan: ScanMessage) -> None:
        ranges = tuple(
            r if echo else math.inf for r, echo in zip(scan.ranges_m, scan.echo, strict=True)
        )
        self._ring(scan.robot_id, scan.stamp_s, ranges)

    def _on_sense(self, _key: str, frame: SenseFrame) -> None:
        if frame.sonar_ranges_m:
            self._ring(frame.robot_id, frame.t_s, frame.sonar_ranges_m)

    # --- what ROS 2 sends ---------------------------------------------------------------

    def _operate(self) -> None:
        """The newest twist and goal ROS 2 sent since the last round, to the robot that
        leads, in one operator command.
        """
        twist = self._newest("cmd_vel", self._twist_of)
        goal = self._newest("goal_pose", self._goal_of)
        if twist is None and goal is None:
            return
        leader = self._leader()
        if leader is None:
            self._refuse("operator", "nobody leads yet: no robot's state heard")
            return
        try:
            command = OperatorCommand(
                robot_id=leader, stamp_s=time.time(), twist=twist is not None,
                v_mps=twist.v_mps if twist else 0.0,
                omega_radps=twist.omega_radps if twist else 0.0,
                goal=goal is not None, goal_x_m=goal.x_m if goal else 0.0,
                goal_y_m=goal.y_m if goal else 0.0,
            )  # fmt: skip
        except ValidationError as exc:
            self._refuse("operator", f"not a command a robot takes: {exc.errors()[0]['msg']}")
            return
        self._session.publish(robot_key(self._fleet, leader, "operator"), command)
        self.stats.sent["operator"] += 1

    def _newest(self, kind: str, read: Callable[[Any], Any]) -> Any:
        """The newest of what arrived on input `kind` that `read` makes a value of (it
        raises ValueError for one the bridge refuses); None: none.
        """
        subscription = self._subs.get(kind)
        if subscription is None:
            return None
        newest = None
        for payload in subscription.take():
            self.stats.heard[kind] += 1
            try:
                newest = read(from_cdr(payload, subscription.topic.ros_type, self.cfg.distro))
            except Exception as exc:  # a hostile payload may trip anything: count it
                self._refuse(kind, f"{type(exc).__name__}: {str(exc)[:200]}")
        return newest

    def _twist_of(self, message: Any) -> Twist2D:
        """A twist to pass on: finite, clamped to the robot's rating (the robot's own
        limits then hold it to the run's).
        """
        twist = planar_twist(message)
        if not (math.isfinite(twist.v_mps) and math.isfinite(twist.omega_radps)):
            raise ValueError(f"a twist that is not finite: {twist}")
        v_max, w_max = self.robot.v_max_mps, self.robot.omega_max_radps
        return Twist2D(
            min(v_max, max(-v_max, twist.v_mps)), min(w_max, max(-w_max, twist.omega_radps))
        )

    def _goal_of(self, message: Any) -> Vec2:
        """A goal to pass on: in the map frame, finite and within the world's extent."""
        frame, goal = stamped_position(message)
        if frame != self.cfg.map_frame:
            raise ValueError(f"a goal in frame {frame[:40]!r}, not {self.cfg.map_frame!r}")
        if not (abs(goal.x_m) <= MAX_EXTENT_M and abs(goal.y_m) <= MAX_EXTENT_M):
            raise ValueError(f"a goal out of the world: {goal}")
        return goal

    def _leader(self) -> str | None:
        """The robot that leads, as the newest state heard says (None: none heard)."""
        states = [h.state for h in self._robots.values() if h.state is not None]
        if not states:
            return None
        newest = max(states, key=lambda s: s.stamp_s)
        return newest.formation_leader_id or self._formation.root

    def _refuse(self, kind: str, why: str) -> None:
        self.stats.refused[kind] += 1
        self.stats.last_refusal = f"{kind}: {why}"

    # --- what goes out --------------------------------------------------------------------

    def round(self) -> int:
        """Take what arrived and publish it; how many ROS messages went out."""
        start_cpu = time.process_time()
        before = sum(self.stats.sent.values())
        self._take()
        self._operate()
        now = time.monotonic()
        moved = [self._robot_round(rid, held, now) for rid, held in self._robots.items()]
        fresh = [(held, state) for held, state in moved if state is not None]
        if fresh and self._wanted("tf"):
            t_s = max(state.stamp_s for _, state in fresh)
            self._tf.transforms = [held.messages.link(t_s, state.pose) for held, state in fresh]
            self._send("tf", "", self._tf)
        if now - self._markers_at >= SLOW_PERIOD_S:
            self._publish_markers(now)
        self.stats.rounds += 1
        self.stats.cpu_s += time.process_time() - start_cpu
        return sum(self.stats.sent.values()) - before

    def _robot_round(self, rid: str, held: _Robot, now: float) -> tuple[_Robot, RobotState | None]:
        """Publish robot `rid`'s news; with its state if it is new (for its TF link)."""
        messages = held.messages
        sonar = self._pubs.get(("sonar", rid))
        if held.ranges_fresh and sonar is not None:
            held.ranges_fresh = False
            self._send_cdr(sonar, messages.sonar_cdr(held.ranges_stamp_s, held.ranges))
        state = held.state
        if state is None:
            return held, None
        if state.fsm_state != held.said or now - held.said_at >= SLOW_PERIOD_S:
            if self._wanted("state", rid):
                self._send("state", rid, messages.text(state.fsm_state))
            held.said, held.said_at = state.fsm_state, now
        if not held.fresh:
            return held, None
        held.fresh = False
        odom = self._pubs.get(("odom", rid))
        if odom is not None:
            cdr = messages.odometry_cdr(
                state.stamp_s, pose=state.pose, twist=state.twist, cov=state.cov
            )
            self._send_cdr(odom, cdr)
        command = self._pubs.get(("cmd_vel_out", rid))
        if command is not None:
            self._send_cdr(command, messages.twist_cdr(state.twist))
        return held, state

    def _publish_markers(self, now: float) -> None:
        states = [h.state for h in self._robots.values() if h.state is not None]
        if not self._wanted("markers") or not states:
            return
        self._markers_at = now
        newest = max(states, key=lambda s: s.stamp_s)
        leader_id = newest.formation_leader_id or self._formation.root
        leader = self._robots.get(leader_id)
        if leader is None or leader.state is None:
            return
        slots = slot_positions(self._formation.positions, leader_id, leader.state.pose)
        self._send("markers", "", self._markers.fill(newest.stamp_s, slots))

    def run(self, stop: Any, *, duration_s: float = math.inf) -> None:
        """Publish `/tf_static`, then a round every 1/`rate_hz` s until `stop` is set (a
        `threading.Event` or `phalanx.runtime.signals.SignalStop`) or `duration_s` passes.
        """
        self.publish_static()
        period_s = 1.0 / self.cfg.rate_hz
        ends = time.monotonic() + duration_s
        next_at = time.monotonic()
        while not stop.is_set() and time.monotonic() < ends:
            self.round()
            next_at = max(next_at + period_s, time.monotonic())
            stop.wait(min(next_at, ends) - time.monotonic())


class _Inbox(Generic[M]):
    """The bridge's subscription to one kind of phalanx message: Zenoh keeps the newest
    `capacity` samples in a ring of its own (`zenoh.handlers.RingChannel`: no Python runs
    on Zenoh's threads, and what the ring drops is not counted), and `drain`, on the
    bridge's thread, decodes and checks them as every subscription of a fleet session does
    (`phalanx.wire.delivery.deliver`, counted in the session's `DecodeStats`).
    """

    def __init__(
        self, session: FleetSession, key_expr: str, model: type[M], capacity: int, *,
        context: Any,
    ) -> None:  # fmt: skip
        import zenoh

        ring: Any = zenoh.handlers.RingChannel(capacity)
        self._subscriber = session.hold(session.zenoh.declare_subscriber(key_expr, ring))
        self._model, self._stats, self._context = model, session.stats, context
        self._capacity = capacity

    def drain(self, on_message: Callable[[str, M], None]) -> int:
        """Call `on_message(key, value)` for every valid message waiting (at most a ring's
        worth: what arrives meanwhile waits for the next call); how many were taken.
        """
        taken = 0
        while taken < self._capacity:
            sample = self._subscriber.try_recv()
            if sample is None:
                break
            payload = sample.payload.to_bytes()
            key = str(sample.key_expr)
            deliver(key, payload, self._model, self._stats, on_message, self._context)
            taken += 1
        return taken


def slot_positions(
    positions: Any, leader_id: str, leader_pose: Pose2D
) -> list[tuple[float, float]]:
    """Every slot of the formation (`positions`: robot -> Vec2 in the formation frame),
    in the world, laid out from the formation leader at `leader_pose`.
    """
    origin: Vec2 = positions[leader_id]
    out = []
    for position in positions.values():
        world = leader_pose.to_world(position - origin)
        out.append((world.x_m, world.y_m))
    return out
