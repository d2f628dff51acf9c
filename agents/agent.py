"""The agent core: one robot's brain as a pure object, `step(observation, peers, t, flags)`.

It does no I/O. The in-process batch runner calls it directly; the multi-process runtime
calls it between a Zenoh read and a driver write. Both feed it the same things, so a
scenario gives the same trajectory either way.

A step: leadership from every robot's flags (`phalanx.agents.leadership`), whom to
track, what the sonar says (`phalanx.agents.perception`), one update of the behaviour
state machine (`phalanx.agents.behaviours.stack`), the active behaviour's command, the
limiter. Group decisions (leadership, deadlock) read only the flags, including the
robot's own as it published them, so every robot takes them from the same data.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from phalanx.agents.behaviours.navigation import (
    REORIENT_RAD,
    Breadcrumbs,
    Clearances,
    ScriptedProfile,
    Wander,
    bearing_rad,
    centring_rad,
    reverse_twist,
    rigid_limit,
    steer,
    turn_rate_radps,
)
from phalanx.agents.behaviours.stack import (
    OUT_OF_FORMATION,
    Plan,
    StackContext,
    behaviour_machine,
)
from phalanx.agents.control import make_controller
from phalanx.agents.control.common import FollowerInput
from phalanx.agents.control.limits import CommandLimiter
from phalanx.agents.leadership import (
    Flags,
    Leadership,
    LeadershipChange,
    LiveFlags,
    group_deadlock,
)
from phalanx.agents.mapping import OccupancyMap
from phalanx.agents.perception import (
    HEADINGS_RAD,
    FloatArray,
    SonarGeometry,
    braking_gap_m,
    clearance_along,
    corridor_clearance,
    nearest_m,
    open_side,
)
from phalanx.core.config import RobotParams, Scenario
from phalanx.core.formation import Formation
from phalanx.core.geometry import ZERO_TWIST, Pose2D, Twist2D, Vec2, wrap_angle
from phalanx.core.limits import KinematicLimits
from phalanx.core.rigid_body import predict_leader, rigid_body_target
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.core.states import State, TransitionEvent
from phalanx.wire.messages import RobotFlags, RobotState

STANDSTILL_MPS = 0.01
# Sonar echoes this close to where a known robot should be are that robot, not an
# obstacle: the tracked robot's position is known (its state), the others' expected.
TRACKED_MASK_M = 0.1
EXPECTED_MASK_M = 0.15
# The emergency stop's corridor hugs the body: a wall passed alongside must not stop it.
ESTOP_MARGIN_M = 0.02
# A follower going round an obstacle aims this far ahead of its moving slot.
AVOID_LEAD_S = 1.0
# Back in formation: within `leadership.formed_m` of the slot and this of its heading.
FORMED_RAD = math.radians(15.0)
# A follower on its slot aligns its heading once its leader has stood still this long
# (below these speeds), turning at this gain.
ALIGN_AFTER_S = 1.0
STILL_MPS = 0.005
STILL_RADPS = 0.005
ALIGN_GAIN_PER_S = 1.0
# Pure pursuit distance of the deadlock reverse along the recorded path.
REVERSE_LOOKBACK_M = 0.6
# An emergency stop ends with this much room beyond the braking distance, not less.
RELEASE_MARGIN_M = 0.1
# A follower this close along its heading to its slot goes the way the slot goes.
INTENT_M = 0.05
# Left and right, for the formation's room to either side.
SIDEWAYS_RAD = np.array([math.pi / 2, -math.pi / 2])
# Room beyond the swept disc a turn on the spot needs (m).
SWEEP_MARGIN_M = 0.35
# A route leading further round than this from the heading goes back the way it came.
BEHIND_RAD = math.radians(100.0)
# A robot whose route turns off by more than this cannot lead on from where it is.
REORIENT_ROUTE_RAD = math.radians(60.0)
# Route re-planning period (s) and how far along the route to head for (m).
REPLAN_S = 1.0
ROUTE_AHEAD_M = 2.0
# A turn on the spot is done within this of the heading it was for.
REORIENTED_RAD = math.radians(10.0)
# The fixed deadlock reverse first turns the shape back to the way it came in (measured
# over this much path) to within this, for at most this long; only from at most this far
# round, which the shape has just swept through (a larger turn back is not known free).
CAME_IN_OVER_M = 2.0
REALIGNED_RAD = math.radians(1.0)
REALIGN_MAX_S = 20.0
REALIGN_MAX_RAD = math.radians(45.0)
# A navigating leader that has not got this far from where it was in `stall_s` is stuck.
PROGRESS_M = 0.3
Points = tuple[FloatArray, FloatArray]


@dataclass(frozen=True, slots=True)
class Observation:
    """What a robot senses this step (from its driver)."""

    odometry: Odometry
    status: RobotStatus


@dataclass(frozen=True, slots=True)
class StepOutput:
    """An agent step's result: the command to send, the state to publish, what changed.

    `leadership` is set on the step this robot took the lead (for the runtime to
    announce on `phalanx/<fleet>/leader`).
    """

    command: Twist2D
    state: RobotState
    events: tuple[TransitionEvent, ...] = field(default_factory=tuple)
    leadership: LeadershipChange | None = None

    @property
    def flags(self) -> RobotFlags:
        """The behaviour flags every other robot needs."""
        return self.state.flags()


@dataclass(frozen=True, slots=True)
class Sensing:
    """A step's reading of the sonar ring and bumpers."""

    points: Points  # known robots removed
    raw: Points  # every echo
    ahead_m: float  # own free way straight ahead
    blocked: dict[int, bool]  # path blocked, forwards (+1) and backwards (-1)
    path_clear: bool
    imminent: bool
    bumper: bool
    dead_end: bool = False


def _plan(scenario: Scenario) -> Plan:
    if scenario.leader_profile is not None:
        return "scripted"
    return "goto" if scenario.navigation.waypoints else "wander"


class Agent:
    """One robot: leadership, the behaviour stack (navigation over formation), limits."""

    def __init__(
        self,
        robot_id: str,
        *,
        scenario: Scenario,
        robot: RobotParams,
        formation: Formation,
        joining: bool = False,
    ) -> None:
        self.robot_id = robot_id
        self.scenario = scenario
        self.formation = formation
        self.nav = scenario.navigation
        self.limits = KinematicLimits.from_params(robot, scenario.limits)
        self.limiter = CommandLimiter(self.limits)
        self.controller = make_controller(scenario.controller)
        self.sonar = SonarGeometry.from_params(robot)
        self.radius_m = robot.radius_m
        self.plan = _plan(scenario)
        self.profile = ScriptedProfile(scenario.leader_profile) if scenario.leader_profile else None
        self.wander = Wander(self.nav, scenario.seed + formation.robot_ids.index(robot_id))
        self.leadership = Leadership(
            robot_id, formation, scenario.leadership, timeout_s=scenario.leader_timeout_s
        )
        self.ctx = StackContext(
            plan=self.plan,
            reactive=self.nav.reactive,
            joined=not joining,
            safe_distance_m=scenario.deadlock.safe_distance_m,
            confirm_s=self.nav.confirm_s,
            threshold_mps=scenario.controller.reverse_threshold_mps,
        )
        self.fsm = behaviour_machine(self._initial_state(joining))
        self.parent_id = formation.leader_of(robot_id)
        here = formation.positions[robot_id]
        # Every other robot's slot in this robot's frame (a rigid shape: fixed).
        self._offsets = {r: p - here for r, p in formation.positions.items()}
        self.waypoint = 0
        self.deadlocks = 0
        self.profile_s = 0.0
        self.formed = not joining
        self._seq = 0
        self._started_s: float | None = None
        self._startup_until_s = 0.0
        self._blocked_s = {1: 0.0, -1: 0.0}  # how long the path each way has been blocked
        self._last_forward = ZERO_TWIST
        self._last_odometry: Odometry | None = None
        self._turned_rad = 0.0
        self._turn_target_rad = 0.0
        self._turn_side = 1
        self._escape: Vec2 | None = None
        self._others_busy = False
        self._stopped_before: frozenset[str] = frozenset()
        self._pausing = False  # the deadlock reverse standing still before it backs off
        self._realigned_s = -math.inf  # when the deadlock reverse's turn back was done
        self._leader_still_s = 0.0  # how long the tracked robot has stood still
        self._chosen: float | None = None  # last heading steered for (world frame, rad)
        self._turn_to: float | None = None  # a turn on the spot under way (world frame)
        self._anchor: tuple[Vec2, float] | None = None  # where and when progress was last made
        self.crumbs = Breadcrumbs(2.0 * scenario.deadlock.safe_distance_m)
        self.map: OccupancyMap | None = None  # built from the sonar unless scripted
        self._carrot: Vec2 | None = None  # where the route leads next (world frame)
        self._planned_s = -math.inf
        # The robots near enough in the shape for the sonar to hear (only these are masked).
        audible_m = self.sonar.mount_m + self.sonar.max_range_m + self.radius_m + EXPECTED_MASK_M
        self._maskable = {r: o for r, o in self._offsets.items() if o.norm() < audible_m + 1.0}
        # How far the shape reaches from this robot (what turning on the spot sweeps).
        self._reach_m = max((o.norm() for o in self._offsets.values()), default=0.0)
        self._half_span_m = self._span_from_centre()

    def _span_from_centre(self) -> float:
        """Half the shape's width across its heading, plus a robot radius (m)."""
        ys = [p.y_m for p in self.formation.positions.values()]
        return (max(ys) - min(ys)) / 2 + self.radius_m

    def _initial_state(self, joining: bool) -> str:
        if joining:
            return State.JOIN
        if not self.leadership.is_leader:
            return State.HOLD
        return State.WANDER if self.plan == "wander" else State.NAVIGATE

    # --- what the rest of the system reads ------------------------------------------

    @property
    def state_name(self) -> str:
        """The current behaviour state."""
        return self.fsm.state

    @property
    def direction(self) -> int:
        """+1 forwards, -1 backwards (the deadlock reverse under way, or following one)."""
        if self.fsm.state == State.DEADLOCK_REVERSE:
            return 1 if self._pausing else -1
        return -1 if self.fsm.state == State.FORMATION_REVERSE else 1

    @property
    def transitions(self) -> list[TransitionEvent]:
        """Every transition taken so far."""
        return self.fsm.log

    @property
    def leader_id(self) -> str:
        """The robot leading the formation, in this robot's view."""
        return self.leadership.leader_id

    # --- the step ---------------------------------------------------------------------

    def step(
        self,
        observation: Observation,
        peers: Mapping[str, RobotState],
        t_s: float,
        flags: Flags | None = None,
    ) -> StepOutput:
        """One control step at fleet time `t_s`.

        `peers`: the latest states of other robots (at least the one this robot tracks);
        `flags`: every robot's latest flags (a `RobotFlags`, or a `RobotState`, which carries
        them), this robot's own as published included; when omitted, `peers` serve.
        """
        if self._started_s is None:
            self._started_s = t_s
            self._startup_until_s = t_s + self.scenario.leader_timeout_s
        view: Flags = flags if flags is not None else peers
        live = self.leadership.live(view, t_s)
        was_leader = self.leadership.is_leader
        change = self.leadership.update(live, t_s)
        self._hear(live, t_s)
        self.parent_id = self.leadership.tracked(live)
        lead = self._fresh(peers.get(self.parent_id) if self.parent_id else None, t_s)
        sensing = self._sense(observation, lead, live, t_s)
        self._progress(observation.odometry.pose)
        self._refresh(observation, sensing, lead, live, change, t_s)
        event = self.fsm.update(self.ctx, t_s)
        if event is not None:
            self._enter(event, observation, sensing, t_s)
        wanted = self._wanted(observation, sensing, lead, live, t_s)
        command = self.limiter.apply(wanted, self.scenario.dt_s)
        self._update_formed(observation.odometry.pose, lead, t_s)
        self._last_odometry = observation.odometry
        took = change if self.leadership.is_leader and not was_leader else None
        state = self._state(observation.odometry, command, sensing, t_s)
        return StepOutput(command, state, (event,) if event else (), took)

    # --- leadership, progress ------------------------------------------------------------

    def _fresh(self, state: RobotState | None, t_s: float) -> RobotState | None:
        if state is None or t_s - state.stamp_s > self.scenario.leader_timeout_s:
            return None
        return state

    def _hear(self, live: LiveFlags, t_s: float) -> None:
        """Join once anyone is heard; followers take the group's progress from the leader."""
        others = len(live) - (self.robot_id in live)
        waited_s = t_s - (self._started_s or t_s)
        if others or waited_s >= self.scenario.leadership.join_timeout_s:
            self.ctx.joined = True
        lead = live.get(self.leadership.leader_id)
        if self.leadership.is_leader or lead is None:
            return
        self.waypoint, self.deadlocks, self.profile_s = (
            lead.waypoint,
            lead.deadlocks,
            lead.profile_s,
        )

    def _progress(self, pose: Pose2D) -> None:
        """The leader's waypoint bookkeeping (a reached waypoint resets the retries)."""
        waypoints = self.nav.waypoints
        if self.plan != "goto" or not self.leadership.is_leader:
            return
        if (
            self._escape is not None
            and (pose.position - self._escape).norm() < self.nav.goal_tolerance_m
        ):
            self._escape = None
        while (
            self.waypoint < len(waypoints) and self._to_waypoint(pose) < self.nav.goal_tolerance_m
        ):
            self.waypoint += 1
            self.deadlocks = 0
            self._escape = None

    def _to_waypoint(self, pose: Pose2D) -> float:
        x, y = self.nav.waypoints[self.waypoint]
        return math.hypot(x - pose.x_m, y - pose.y_m)

    # --- sensing ---------------------------------------------------------------------

    def _known_robots(
        self, lead: RobotState | None, live: Flags, t_s: float, pose: Pose2D
    ) -> list[tuple[Vec2, float]]:
        """Body-frame centres (and mask radii) of robots whose echoes are not obstacles:
        the tracked one where its state says it is, the others where the shape expects.
        """
        known: list[tuple[Vec2, float]] = []
        if lead is not None:
            predicted = predict_leader(lead.pose, lead.twist, max(0.0, t_s - lead.stamp_s))
            known.append((pose.to_body(predicted.position), self.radius_m + TRACKED_MASK_M))
        if self.fsm.state not in OUT_OF_FORMATION:
            radius_m = self.radius_m + EXPECTED_MASK_M
            for rid, offset in self._maskable.items():
                flags = live.get(rid)
                # Not heard yet (starting up) counts as in its slot, as the scenario has it.
                in_slot = flags.formed if flags is not None else t_s < self._startup_until_s
                if rid not in (self.robot_id, self.parent_id) and in_slot:
                    known.append((offset, radius_m))
        return known

    def _sense(
        self,
        observation: Observation,
        lead: RobotState | None,
        live: Flags,
        t_s: float,
    ) -> Sensing:
        status, odometry = observation.status, observation.odometry
        ranges = np.asarray(status.sonar_ranges_m, dtype=np.float64)
        every_echo = self.sonar.echoes(ranges)
        raw = self.sonar.points_of(ranges, every_echo)
        echo = self.sonar.echoes(ranges, self._known_robots(lead, live, t_s, odometry.pose))
        # (the usual case, no echo of a robot: the same points, not worked out twice)
        masked = raw if np.array_equal(echo, every_echo) else self.sonar.points_of(ranges, echo)
        if self.plan != "scripted" and self.nav.reactive:
            if self.map is None:
                self.map = OccupancyMap(odometry.pose.position)
            self.map.update(odometry.pose, self.sonar, ranges, echo)
        half_width = self.radius_m + self.nav.body_margin_m
        ahead_m = clearance_along(masked, 0.0, half_width_m=half_width)
        behind_m = clearance_along(masked, math.pi, half_width_m=half_width)
        near_m = self.scenario.deadlock.obstacle_range_m
        bumper = any(status.bumpers)
        dead_end = self._boxed_in(odometry.pose, masked)
        blocked_ahead = ahead_m < near_m or self._stalled(odometry, t_s) or dead_end
        return Sensing(
            points=masked,
            raw=raw,
            ahead_m=ahead_m,
            blocked={1: blocked_ahead or bumper, -1: behind_m < near_m or bumper},
            path_clear=self.direction > 0
            and ahead_m >= self.nav.clear_range_m
            and self._route_ahead(odometry.pose, live, t_s),
            imminent=self.nav.reactive and (bumper or self._imminent(raw, odometry)),
            bumper=bumper,
            dead_end=dead_end,
        )

    def _stalled(self, odometry: Odometry, t_s: float) -> bool:
        """A navigating leader that turns and creeps without getting anywhere is blocked
        as surely as one facing a wall: say so, and the group's rules take over.
        """
        if self.fsm.state not in (State.NAVIGATE, State.WANDER) or self.plan == "scripted":
            self._anchor = None
            return False
        here = odometry.pose.position
        if self._anchor is None or (here - self._anchor[0]).norm() >= PROGRESS_M:
            self._anchor = (here, t_s)
        return t_s - self._anchor[1] >= self.nav.stall_s

    def _route_ahead(self, pose: Pose2D, live: Flags, t_s: float) -> bool:
        """Whether the way to the goal goes on ahead of this robot (so it could lead):
        a follower asks its map only while the leader is blocked and might hand over.
        """
        if self.plan != "goto" or self.map is None or self.waypoint >= len(self.nav.waypoints):
            return True
        if not self.leadership.is_leader:
            head = live.get(self.leadership.leader_id)
            if head is None or not head.obstacle:
                return True
            goal = Vec2(*self.nav.waypoints[self.waypoint])
            carrot = self._route(pose, goal, t_s)
        else:
            carrot = self._carrot or Vec2(*self.nav.waypoints[self.waypoint])
        return abs(bearing_rad(pose, carrot)) <= REORIENT_ROUTE_RAD

    def _sweep_clear(self, points: Points) -> bool:
        """Whether the shape can turn on the spot about this robot: nothing within the
        disc its slots sweep (seen from here).
        """
        return nearest_m(points) > self._reach_m + self.radius_m + SWEEP_MARGIN_M

    def _boxed_in(self, pose: Pose2D, points: Points) -> bool:
        """A navigating leader whose route leads back the way it came, with no room for
        the shape to turn round where it is: the dead end the deadlock reverse is for.
        """
        if self.fsm.state not in (State.NAVIGATE, State.WANDER) or self._carrot is None:
            return False
        behind = abs(bearing_rad(pose, self._carrot)) > BEHIND_RAD
        return behind and not self._sweep_clear(points)

    def _clearances(self, points: Points, live: Flags) -> Clearances:
        """Free way along every candidate heading: own, and (a navigating leader) the
        whole formation's, with its room to either side.
        """
        half_width = self.radius_m + self.nav.body_margin_m
        narrow = corridor_clearance(points, HEADINGS_RAD, half_width_m=half_width)
        if not self.leadership.is_leader or self.plan == "scripted":
            return Clearances(narrow, narrow)
        slots = self._slots(live, origin=True)
        wide = corridor_clearance(points, HEADINGS_RAD, half_width_m=half_width, origins=slots)
        left, right = corridor_clearance(
            points, SIDEWAYS_RAD, half_width_m=half_width, origins=slots, turning=False
        )
        return Clearances(wide, narrow, float(left), float(right))

    def _slots(self, live: Flags, *, origin: bool = False) -> list[Vec2]:
        """Slots of the robots in formation, in this robot's frame (own origin if asked)."""
        slots = [Vec2(0.0, 0.0)] if origin else []
        for rid, f in live.items():
            if rid != self.robot_id and f.formed and f.fsm_state not in OUT_OF_FORMATION:
                slots.append(self._offsets[rid])
        return slots

    def _imminent(self, raw: Points, odometry: Odometry) -> bool:
        """An obstacle (any, robots included) inside the braking distance + margin."""
        last = self.limiter.last
        moving = odometry.twist.v_mps if abs(odometry.twist.v_mps) > STANDSTILL_MPS else last.v_mps
        if abs(moving) <= STANDSTILL_MPS:
            return False  # turning on the spot: a round robot sweeps nothing new
        speed = max(abs(odometry.twist.v_mps), abs(last.v_mps))
        braking = braking_gap_m(
            speed, decel_mps2=self.limits.decel_mps2, latency_s=2 * self.scenario.dt_s
        )
        half_width = self.radius_m + ESTOP_MARGIN_M
        if nearest_m(raw) > braking + self.nav.stop_margin_m + half_width:
            return False  # nothing near enough to matter, whatever the heading
        way = 0.0 if moving > 0 else math.pi
        gap = clearance_along(raw, way, half_width_m=half_width)
        return gap < braking + self.nav.stop_margin_m

    # --- the machine's context and entry actions -----------------------------------

    def _refresh(
        self,
        observation: Observation,
        sensing: Sensing,
        lead: RobotState | None,
        live: LiveFlags,
        change: LeadershipChange | None,
        t_s: float,
    ) -> None:
        c, lsh = self.ctx, self.leadership
        dt_s = self.scenario.dt_s
        for way, blocked in sensing.blocked.items():
            self._blocked_s[way] = self._blocked_s[way] + dt_s if blocked else 0.0
        c.is_leader = lsh.is_leader
        c.arrived = self.plan == "goto" and self.waypoint >= len(self.nav.waypoints)
        if change is not None:
            c.role_reason = f"{change.reason} (epoch {change.epoch}, leader {change.leader_id})"
        c.bumper, c.imminent = sensing.bumper, sensing.imminent
        c.standstill = abs(observation.odometry.twist.v_mps) < STANDSTILL_MPS
        c.way_clear = self.fsm.state != State.EMERGENCY_STOP or self._way_clear(
            sensing, lead, observation.odometry.pose, t_s
        )
        c.blocked_s = self._blocked_s[self.direction]
        head = live.get(lsh.leader_id)
        c.leader_lost = lsh.leader_lost(live)
        c.leader_blocked = head is not None and head.obstacle and not lsh.is_leader
        c.leader_state = head.fsm_state if head is not None else ""
        c.parent_fresh = lead is not None
        c.parent_v_mps = lead.v_mps if lead else 0.0
        c.parent_direction = lead.direction if lead else 1
        stopped = live.stopped - {self.robot_id}
        if self.fsm.state != State.DEADLOCK_REVERSE:
            self._stopped_before = stopped  # stops for what lay ahead are not a reason
        c.someone_stopped = bool(stopped - self._stopped_before)
        self._others_busy = len(live.busy) > (self.robot_id in live.busy)
        self._refresh_deadlock(live)
        self._refresh_motion(observation.odometry)

    def _way_clear(
        self, sensing: Sensing, lead: RobotState | None, pose: Pose2D, t_s: float
    ) -> bool:
        """Room to brake from cruise speed the way this robot means to go (what ends an
        emergency stop): forwards for a leader; for a follower, the way to its slot (or,
        on it, the way its slot moves).
        """
        backwards = False
        if lead is not None and not self.leadership.is_leader:
            target, ff = self._slot_target(lead, t_s)
            offset = target.position - pose.position
            along = offset.x_m * math.cos(pose.theta_rad) + offset.y_m * math.sin(pose.theta_rad)
            backwards = along < -INTENT_M or (abs(along) <= INTENT_M and ff.v_mps < 0.0)
        gap = clearance_along(
            sensing.raw, math.pi if backwards else 0.0, half_width_m=self.radius_m + ESTOP_MARGIN_M
        )
        return gap >= self._stop_gap_m() + RELEASE_MARGIN_M

    def _refresh_deadlock(self, live: Flags) -> None:
        c = self.ctx
        reason = ""
        if self.leadership.is_leader:
            # A scripted leader (the paper's runs) keeps the paper's rule: all blocked.
            reason = group_deadlock(
                live, self.robot_id, confirm_s=self.nav.confirm_s, widened=self.plan != "scripted"
            )
        c.deadlock, c.deadlock_reason = bool(reason), reason
        c.retries_left = self.deadlocks < self.scenario.deadlock.max_retries
        c.stuck_reason = (
            f"{reason}; {self.deadlocks} deadlock reverses already at waypoint "
            f"{self.waypoint} (deadlock.max_retries = {self.scenario.deadlock.max_retries})"
        )

    def _refresh_motion(self, odometry: Odometry) -> None:
        previous = self._last_odometry
        if odometry.twist.v_mps > STANDSTILL_MPS:
            self.crumbs.drop(odometry.pose.position)  # ground just crossed: known free
        if previous is None:
            return
        if self.fsm.state == State.DEADLOCK_REVERSE:
            self.ctx.reversed_m += (odometry.pose.position - previous.pose.position).norm()
        if self.fsm.state == State.DEADLOCK_TURN:
            self._turned_rad += abs(wrap_angle(odometry.pose.theta_rad - previous.pose.theta_rad))
        self.ctx.turned = self._turned_rad >= self._turn_target_rad - 1e-3

    def _enter(
        self, event: TransitionEvent, observation: Observation, sensing: Sensing, t_s: float
    ) -> None:
        state = event.target
        if state in OUT_OF_FORMATION:
            self.formed = False
        if state == State.DEADLOCK_REVERSE:
            self._realigned_s = t_s
            self.ctx.reversed_m = 0.0
            self.ctx.path_used_up = False
            self.deadlocks += 1
        elif state == State.DEADLOCK_TURN:
            self._start_turn(sensing, observation.odometry.pose, t_s)
        elif state == State.AVOID:
            self.ctx.way_free_s = 0.0
        if event.source == State.DEADLOCK_TURN:
            self._blocked_s = {1: 0.0, -1: 0.0}  # a new heading: blocked if blocked again
            if self.plan == "goto" and self.map is None:
                # Leave the dead end along the new heading before making for the goal.
                ahead = Vec2(self.scenario.deadlock.escape_distance_m, 0.0)
                self._escape = observation.odometry.pose.to_world(ahead)
        if state not in (State.NAVIGATE, State.WANDER, State.AVOID):
            self._chosen = None
            self._turn_to = None
            self._carrot = None
        self._anchor = None

    def _start_turn(self, sensing: Sensing, pose: Pose2D, t_s: float) -> None:
        """Turn towards the route if the map has one, else towards the more open side by
        `turn_away_deg` per deadlock at this waypoint.
        """
        half_width = self.radius_m + self.nav.body_margin_m
        self._turn_side = open_side(sensing.points, half_width_m=half_width)
        angle = math.radians(self.scenario.deadlock.turn_away_deg) * max(1, self.deadlocks)
        if self.plan == "goto" and self.map is not None:
            self._carrot = None
            goal = Vec2(*self.nav.waypoints[min(self.waypoint, len(self.nav.waypoints) - 1)])
            towards = bearing_rad(pose, self._route(pose, goal, t_s))
            self._turn_side, angle = (1 if towards >= 0.0 else -1), abs(towards)
        self._turn_target_rad = min(math.pi, angle)
        self._turned_rad = 0.0
        self.ctx.turned = self._turn_target_rad <= REORIENTED_RAD

    def _update_formed(self, pose: Pose2D, lead: RobotState | None, t_s: float) -> None:
        state = self.fsm.state
        if self.leadership.is_leader and state not in OUT_OF_FORMATION:
            self.formed = True
        elif state in OUT_OF_FORMATION:
            self.formed = False
        elif not self.formed and lead is not None and state != State.HOLD:
            target, _ = self._slot_target(lead, t_s)
            error_m = (pose.position - target.position).norm()
            error_rad = abs(wrap_angle(pose.theta_rad - target.theta_rad))
            self.formed = error_m < self.scenario.leadership.formed_m and error_rad < FORMED_RAD

    # --- commands ----------------------------------------------------------------------

    def _wanted(
        self,
        observation: Observation,
        sensing: Sensing,
        lead: RobotState | None,
        live: Flags,
        t_s: float,
    ) -> Twist2D:
        state, pose = self.fsm.state, observation.odometry.pose
        if state in (State.NAVIGATE, State.WANDER):
            return self._navigate(pose, sensing, live, t_s)
        if state == State.DEADLOCK_REVERSE:
            return self._reverse(pose, t_s)
        if state == State.DEADLOCK_TURN:
            return Twist2D(0.0, self._turn_side * self._turn_rate())
        if lead is None:
            return ZERO_TWIST
        if state in (State.FORMATION_TRACK, State.FORMATION_REVERSE):
            return self._track(observation.odometry, lead, t_s)
        if state == State.AVOID:
            return self._avoid(pose, sensing, lead, t_s)
        return ZERO_TWIST  # HOLD, JOIN, ARRIVED, EMERGENCY_STOP, STUCK

    def _navigate(self, pose: Pose2D, sensing: Sensing, live: Flags, t_s: float) -> Twist2D:
        if self.plan == "scripted" and self.profile is not None:
            twist = self.profile.twist_at(self.profile_s)
            self.profile_s += self.scenario.dt_s
            self._last_forward = twist
            return twist
        if self.fsm.state == State.WANDER or self.plan == "wander":
            heading = self.wander.heading(pose, t_s)
            desired, dist_m = wrap_angle(heading - pose.theta_rad), math.inf
        else:
            goal = self._escape or Vec2(*self.nav.waypoints[self.waypoint])
            dist_m = (goal - pose.position).norm()
            desired = bearing_rad(pose, self._route(pose, goal, t_s))
        speed = min(self.nav.cruise_mps, 0.5 * dist_m + 0.02)
        if self._others_busy:
            speed *= self.nav.slowdown  # give robots off their slots a chance to catch up
        if self._turn_to is not None and not self._sweep_clear(sensing.points):
            self._turn_to = None  # no room to swing the shape round here after all
        if self._turn_to is not None:  # finish a turn on the spot before choosing again
            error = wrap_angle(self._turn_to - pose.theta_rad)
            if abs(error) > REORIENTED_RAD:
                rate = min(self._turn_rate(), self.nav.heading_gain_per_s * abs(error))
                return Twist2D(0.0, math.copysign(rate, error))
            self._turn_to = None
        previous = None if self._chosen is None else wrap_angle(self._chosen - pose.theta_rad)
        clearances = self._clearances(sensing.points, live)
        room_to_turn = self._sweep_clear(sensing.points)
        twist, chosen = steer(
            desired + centring_rad(clearances),
            clearances,
            nav=self.nav,
            speed_mps=speed,
            stop_gap_m=self._stop_gap_m(),
            need_m=min(self.nav.lookahead_m, dist_m + self.radius_m),
            omega_max_radps=self._turn_rate(),
            previous_rad=previous,
            min_radius_m=self.nav.min_turn_radius_m,
            reach_rad=math.pi if room_to_turn else REORIENT_RAD,
        )
        self._chosen = pose.theta_rad + chosen
        if twist.v_mps == 0.0 and twist.omega_radps != 0.0 and room_to_turn:
            self._turn_to = self._chosen
        twist = rigid_limit(twist, self._follower_slots(), self.limits.v_max_mps)
        self._last_forward = twist
        return twist

    def _reverse(self, pose: Pose2D, t_s: float) -> Twist2D:
        deadlock = self.scenario.deadlock
        realign = self._realign(pose, t_s)
        if realign is not None:
            self._pausing = True
            self._realigned_s = t_s
            return realign
        self._pausing = t_s - self._realigned_s < deadlock.pause_s - 1e-9
        if self._pausing:
            return ZERO_TWIST  # stand still first: the followers settle on their slots
        if deadlock.reverse_mode != "path":
            return reverse_twist(deadlock, self._last_forward)
        twist = self.crumbs.back_along(pose, deadlock.reverse_speed_mps, REVERSE_LOOKBACK_M)
        if twist is None:  # backed along all the ground it knows: go no further
            self.ctx.path_used_up = True
            return ZERO_TWIST
        return twist

    def _realign(self, pose: Pose2D, t_s: float) -> Twist2D | None:
        """A navigating group caught in a deadlock while turning: turn the shape back to
        the way it came in before backing out straight (else it backs out diagonally).
        """
        deadlock = self.scenario.deadlock
        if deadlock.reverse_mode != "fixed" or self.plan != "goto":
            return None
        if t_s - self._realigned_s >= deadlock.pause_s:
            return None  # backing out already
        came_in = self.crumbs.heading_in_rad(CAME_IN_OVER_M)
        if came_in is None or t_s - self.fsm.entered_at_s > REALIGN_MAX_S:
            return None
        error = wrap_angle(came_in - pose.theta_rad)
        if not REALIGNED_RAD < abs(error) <= REALIGN_MAX_RAD:
            return None
        rate = min(self._turn_rate(), self.nav.heading_gain_per_s * abs(error))
        return Twist2D(0.0, math.copysign(rate, error))

    def _route(self, pose: Pose2D, goal: Vec2, t_s: float) -> Vec2:
        """Where to head for next: along the cheapest route round everything the sonar
        has shown so far (re-planned every `REPLAN_S`), which keeps the shape's half-width
        off obstacles where there is room and squeezes by where there is not (followers
        go round what the shape does not clear); straight for the goal without a map.
        """
        if self.map is None:
            return goal
        if t_s - self._planned_s >= REPLAN_S or self._carrot is None:
            self._planned_s = t_s
            self._carrot = self.map.route(
                pose.position, goal, keep_off_m=self._half_span_m, ahead_m=ROUTE_AHEAD_M
            )
        return self._carrot or goal

    def _follower_slots(self) -> list[Vec2]:
        return [p for r, p in self._offsets.items() if r != self.robot_id]

    def _turn_rate(self) -> float:
        return turn_rate_radps(
            self._follower_slots(), self.limits.v_max_mps, self.limits.omega_max_radps
        )

    def _stop_gap_m(self) -> float:
        braking = braking_gap_m(
            self.nav.cruise_mps, decel_mps2=self.limits.decel_mps2, latency_s=2 * self.scenario.dt_s
        )
        return braking + self.nav.stop_margin_m

    def _slot_target(self, lead: RobotState, t_s: float) -> tuple[Pose2D, Twist2D]:
        age_s = max(0.0, t_s - lead.stamp_s)
        leader = predict_leader(lead.pose, lead.twist, age_s)
        slot = self.formation.slot_of(self.robot_id, lead.robot_id)
        return rigid_body_target(leader, lead.twist, slot)

    def _track(self, odometry: Odometry, lead: RobotState, t_s: float) -> Twist2D:
        still = abs(lead.v_mps) < STILL_MPS and abs(lead.omega_radps) < STILL_RADPS
        self._leader_still_s = self._leader_still_s + self.scenario.dt_s if still else 0.0
        if self._leader_still_s >= ALIGN_AFTER_S:
            aligned = self._align(odometry.pose, lead, t_s)
            if aligned is not None:
                return aligned
        inp = FollowerInput(
            follower=odometry.pose,
            follower_twist=odometry.twist,
            leader=lead.pose,
            leader_twist=lead.twist,
            leader_age_s=max(0.0, t_s - lead.stamp_s),
            slot=self.formation.slot_of(self.robot_id, lead.robot_id),
            direction=self.direction,
            dt_s=self.scenario.dt_s,
        )
        return self.controller.command(inp)

    def _align(self, pose: Pose2D, lead: RobotState, t_s: float) -> Twist2D | None:
        """On its slot beside a leader standing still, turn on the spot to the slot's heading.

        Tracking a point aims the robot's position, not its heading, and a still target
        leaves any heading error where it is: the group's next move, a reverse out of a
        dead end say, would start with it.
        """
        target, _ = self._slot_target(lead, t_s)
        if (pose.position - target.position).norm() > self.scenario.leadership.formed_m:
            return None
        error = wrap_angle(target.theta_rad - pose.theta_rad)
        rate = min(self.limits.omega_max_radps, ALIGN_GAIN_PER_S * abs(error))
        return Twist2D(0.0, math.copysign(rate, error))

    def _avoid(self, pose: Pose2D, sensing: Sensing, lead: RobotState, t_s: float) -> Twist2D:
        """Round the obstacle towards a point a little ahead of the moving slot."""
        target, ff = self._slot_target(lead, t_s)
        lead_m = ff.v_mps * AVOID_LEAD_S
        aim = target.position + Vec2(
            lead_m * math.cos(target.theta_rad), lead_m * math.sin(target.theta_rad)
        )
        desired, dist_m = bearing_rad(pose, aim), (aim - pose.position).norm()
        half_width = self.radius_m + self.nav.body_margin_m
        way_m = clearance_along(sensing.points, desired, half_width_m=half_width)
        free = way_m >= min(dist_m, self.nav.clear_range_m) and not sensing.blocked[1]
        self.ctx.way_free_s = self.ctx.way_free_s + self.scenario.dt_s if free else 0.0
        speed = min(0.9 * self.limits.v_max_mps, 0.5 * dist_m + abs(ff.v_mps))
        narrow = corridor_clearance(sensing.points, HEADINGS_RAD, half_width_m=half_width)
        previous = None if self._chosen is None else wrap_angle(self._chosen - pose.theta_rad)
        twist, chosen = steer(
            desired,
            Clearances(narrow, narrow),
            nav=self.nav,
            speed_mps=speed,
            stop_gap_m=self._stop_gap_m(),
            need_m=min(dist_m, self.nav.lookahead_m),
            omega_max_radps=self.limits.omega_max_radps,
            previous_rad=previous,
        )
        self._chosen = pose.theta_rad + chosen
        return twist

    # --- what the robot publishes ------------------------------------------------------

    def _state(
        self, odometry: Odometry, command: Twist2D, sensing: Sensing, t_s: float
    ) -> RobotState:
        # The published twist is the command being executed from t_s on: a follower that
        # dead-reckons over the state's age then lands where the leader really is.
        self._seq += 1
        pose = odometry.pose
        return RobotState(
            robot_id=self.robot_id,
            seq=self._seq,
            stamp_s=t_s,
            x_m=pose.x_m,
            y_m=pose.y_m,
            theta_rad=pose.theta_rad,
            v_mps=command.v_mps,
            omega_radps=command.omega_radps,
            fsm_state=self.state_name,
            obstacle=sensing.blocked[self.direction],
            direction=1 if self.direction > 0 else -1,
            leader_id=self.parent_id or "",
            epoch=self.leadership.epoch,
            formation_leader_id=self.leadership.leader_id,
            clear=sensing.path_clear,
            formed=self.formed,
            blocked_s=self._blocked_s[self.direction],
            dead_end=sensing.dead_end,
            waypoint=self.waypoint,
            deadlocks=self.deadlocks,
            profile_s=self.profile_s,
        )
