"""The agent: one robot's brain as a pure object, `step(observation, peers, t, flags)`.

It does no I/O. The in-process batch runner calls it directly; the agent runtime calls
it between a Zenoh read and a driver write. Both feed it the same things, so a scenario
gives the same trajectory either way.

A step, in order:
1. **listen**: leadership from every robot's flags (`phalanx.agents.leadership`), whom
   to track and that robot's latest state;
2. **sense**: what the sonar ring and bumpers say (`phalanx.agents.sensing`);
3. **estimate**: the pose estimator (`phalanx.agents.estimation`, when the scenario's
   `[localisation]` turns it on) fuses odometry with the positioning measurements, right
   after listening (relative measurements need the tracked robot's state) and before
   sensing (which places the sonar echoes with the pose); later the memories move on
   (waypoints, blocked timers, the path crossed, the active behaviour's progress);
4. **decide**: the guards' context is built once, and the behaviour state machine
   (`phalanx.agents.behaviours.stack`) takes at most one transition (an operator's
   twist in the observation, while young enough, puts a leader in TELEOP);
5. **command**: the active state's behaviour turns the step into a twist;
6. **limit**: the limiter saturates and rate-limits it.

Group decisions (leadership, deadlock) read only the flags, including the robot's own as
it published them, so every robot takes them from the same data. Everything a runtime or
the batch runner needs of a step is in its `StepOutput`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from phalanx.agents.behaviours.base import Behaviour, Moment
from phalanx.agents.behaviours.context import StackContext
from phalanx.agents.behaviours.stack import behaviour_machine
from phalanx.agents.control.limits import CommandLimiter
from phalanx.agents.control.spacing import Spacing
from phalanx.agents.estimation.estimator import PoseEstimator
from phalanx.agents.estimation.landmarks import Landmarks
from phalanx.agents.fsm import StateMachine
from phalanx.agents.inputs import FleetView, Observation, now
from phalanx.agents.leadership import Flags, Leadership, LeadershipChange, group_deadlock
from phalanx.agents.masking import MaskInputs, SlotMasks
from phalanx.agents.parts import Parts
from phalanx.agents.sensing import (
    STANDSTILL_MPS,
    ContactGuard,
    Sensing,
    Stance,
    clear_towards,
    way_clear,
)
from phalanx.core.config import Scenario
from phalanx.core.formation import Formation
from phalanx.core.geometry import ZERO_TWIST, Pose2D, Twist2D, wrap_angle
from phalanx.core.limits import run_limits
from phalanx.core.mapfile import GridMap
from phalanx.core.peers import PeerFlags, PeerState, Scan
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.core.robot_params import RobotParams
from phalanx.core.states import OUT_OF_FORMATION, State, TransitionEvent

__all__ = ["Agent", "Observation", "StepOutput"]

# Back in formation: within `Shape.formed_within_m` of the slot and this of its heading.
FORMED_RAD = math.radians(15.0)
# A robot stopped for a low battery goes on once it is this far above the mark.
BATTERY_HYSTERESIS_V = 0.3
# Two robots' bodies count as too close at this much less than a body's width apart (the
# room the pose estimates' errors and a step's delay need).
SPACING_MARGIN_M = 0.1


@dataclass(frozen=True, slots=True)
class StepOutput:
    """An agent step's result: the command to send, the state to publish, what changed,
    and the counters a run reports (`saturations`, `accel_limited`: the limiter's
    interventions so far).

    `leadership` is set on the step this robot took the lead (for the runtime to
    announce on `phalanx/<fleet>/leader`).
    """

    command: Twist2D
    state: PeerState
    events: tuple[TransitionEvent, ...] = field(default_factory=tuple)
    leadership: LeadershipChange | None = None
    saturations: int = 0
    accel_limited: int = 0
    scan: Scan | None = None  # this step's sonar reading, for the fleet's shared map

    @property
    def flags(self) -> PeerFlags:
        """The behaviour flags every other robot needs."""
        return self.state.flags()


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
        prior_map: GridMap | None = None,
    ) -> None:
        self.robot_id, self.scenario, self.robot = robot_id, scenario, robot
        self.dt_s = scenario.dt_s
        self.limits = run_limits(robot, scenario.limits)
        self.limiter = CommandLimiter(self.limits)
        self.contact = ContactGuard(
            robot.radius_m, self.dt_s, self.limits.v_max_mps, on=scenario.navigation.reactive
        )
        self.spacing = Spacing(
            robot_id,
            contact_m=2.0 * robot.radius_m + SPACING_MARGIN_M,
            decel_mps2=self.limits.emergency_decel_mps2,
            latency_s=2.0 * self.dt_s,
        )
        self.leadership = Leadership(
            robot_id, formation, scenario.leadership, timeout_s=scenario.leader_timeout_s,
            joining=joining,
        )  # fmt: skip
        self.parts = Parts(robot_id, scenario, robot, formation, self.limits, prior_map)
        self.fsm: StateMachine[StackContext] = behaviour_machine(self._initial_state(joining))
        self.parent_id = formation.leader_of(robot_id)
        self.formed = not joining
        self.joined = not joining
        self.role_reason = ""
        self._seq = 0
        self._last_odometry: Odometry | None = None
        self._heard: tuple[float, FleetView, Observation] | None = None
        self.view: FleetView | None = None  # the fleet as the last step perceived it
        self._last_forward = ZERO_TWIST  # the forward twist a behaviour drove last
        self.estimator: PoseEstimator | None = None
        if scenario.localisation.estimator:
            self.estimator = PoseEstimator(
                scenario.localisation, track_m=robot.track_width_m, robot_id=robot_id
            )
        self._cov: tuple[float, ...] = ()
        self.landmarks = Landmarks(formation, robot_id)

    def _initial_state(self, joining: bool) -> str:
        if joining:
            return State.JOIN
        if not self.leadership.is_leader:
            return State.HOLD
        return State.WANDER if self.parts.plan == "wander" else State.NAVIGATE

    # --- what the rest of the system reads ------------------------------------------

    @property
    def state_name(self) -> str:
        """The current behaviour state."""
        return self.fsm.state

    @property
    def direction(self) -> int:
        """+1 forwards, -1 backwards (the deadlock reverse under way, or following one, or
        an operator driving it backwards).
        """
        if self.fsm.state == State.DEADLOCK_REVERSE:
            return 1 if self.parts.reverse.pausing else -1
        if self.fsm.state == State.TELEOP:
            return -1 if self.limiter.last.v_mps < -STANDSTILL_MPS else 1
        return -1 if self.fsm.state == State.FORMATION_REVERSE else 1

    @property
    def transitions(self) -> list[TransitionEvent]:
        """Every transition taken so far."""
        return self.fsm.log

    @property
    def leader_id(self) -> str:
        """The robot leading the formation, in this robot's view."""
        return self.leadership.leader_id

    @property
    def robot_echoes_left_out(self) -> int:
        """The sonar echoes this robot's copy of the fleet's map has left out as another
        robot of the fleet, not an obstacle (0 without a map).
        """
        fleet = self.parts.planner.fleet
        return 0 if fleet is None else fleet.robot_echoes

    @property
    def _active(self) -> Behaviour:
        return self.parts.behaviours[self.fsm.state]

    # --- the step ---------------------------------------------------------------------

    def step(
        self,
        observation: Observation,
        peers: Mapping[str, PeerState],
        t_s: float,
        flags: Flags | None = None,
    ) -> StepOutput:
        """One control step at fleet time `t_s`.

        `peers`: the latest states of other robots (at least the one this robot tracks);
        `flags`: every robot's latest flags (a `PeerFlags`, or a `PeerState`, which carries
        them), this robot's own as published included; when omitted, `peers` serve.
        """
        self.parts.startup.begin(t_s, self.scenario.leader_timeout_s)
        # perceive the fleet and estimate this robot's pose
        view, observation = self._listen_and_localise(observation, peers, flags, t_s)
        self.view = view
        stance = Stance(self.fsm.state, self.direction, self.limiter.last)
        sensing = self._sense(observation, view, stance, t_s)
        self._estimate(observation, sensing, view, t_s)  # the memories move on
        event, moment = self._decide(observation, sensing, view, stance, t_s)
        wanted = self._command(moment, observation, peers)
        command = self.limiter.apply(
            wanted, self.dt_s, emergency=self._active.emergency, brake_hard=self.spacing.cut
        )
        self._update_formed(observation.odometry.pose, view)
        self._last_odometry = observation.odometry
        return self._output(observation.odometry, command, sensing, view, event, t_s)

    def _sense(
        self, observation: Observation, view: FleetView, stance: Stance, t_s: float
    ) -> Sensing:
        """The sonar and bumpers, read with the step's pose."""
        assume_formed = t_s < self.parts.startup.assume_formed_until_s
        return self.parts.senses.read(
            observation, view, stance, t_s=t_s, assume_formed=assume_formed
        )

    def _decide(
        self,
        observation: Observation,
        sensing: Sensing,
        view: FleetView,
        stance: Stance,
        t_s: float,
    ) -> tuple[TransitionEvent | None, Moment]:
        """At most one transition, on a context built once; the step as the behaviour
        of the state the machine is now in sees it.
        """
        operator = _operator_twist(observation, t_s)
        ctx = self._context(observation, sensing, view, stance, t_s, operator)
        event = self.fsm.update(ctx, t_s)
        moment = Moment(
            t_s, self.fsm.state, observation.odometry, sensing, view, ctx.others_busy,
            self._last_forward, operator,
        )  # fmt: skip
        if event is not None:
            self._enter(event, moment)
        return event, moment

    def _command(
        self, moment: Moment, observation: Observation, peers: Mapping[str, PeerState]
    ) -> Twist2D:
        """The active behaviour's twist (noting the forward twist it reports), kept apart
        from the other robots and off contact; before the limiter.
        """
        active = self._active
        wanted = active.command(moment)
        if active.drove_forward is not None:
            self._last_forward = active.drove_forward
        wanted = self.spacing.apply(wanted, moment.pose, peers, observation.near)
        return self.contact.apply(wanted, moment.sensing)

    # --- listen, estimate -------------------------------------------------------------

    @property
    def slot_masks(self) -> SlotMasks:
        """Where this robot's sonar would hear the formation's others (for `hear`'s use)."""
        return self.parts.senses.slot_masks

    def hear(
        self,
        observation: Observation,
        peers: Mapping[str, PeerState],
        t_s: float,
        flags: Flags | None = None,
    ) -> MaskInputs:
        """The listen stage of the step at `t_s` (and the pose estimate, which sensing
        reads), ahead of it, and what masking the formation's robots out of this robot's
        sonar needs: the batch runner hears every robot first, masks all their readings
        in one pass (`phalanx.agents.masking`) and hands each its own in the
        `Observation`. `step` at `t_s` then goes on from here.
        """
        self.parts.startup.begin(t_s, self.scenario.leader_timeout_s)
        view = self._listen(peers, flags, t_s)
        localised = self._localise(observation, view, peers, t_s)
        self._heard = (t_s, view, localised)
        assume_formed = t_s < self.parts.startup.assume_formed_until_s
        pose = localised.odometry.pose
        return MaskInputs(self.robot_id, view, self.fsm.state, pose, assume_formed, t_s)

    def _listen_and_localise(
        self,
        observation: Observation,
        peers: Mapping[str, PeerState],
        flags: Flags | None,
        t_s: float,
    ) -> tuple[FleetView, Observation]:
        """The fleet as heard at `t_s` and the observation with the pose estimate in it:
        what `hear` worked out ahead of the step (with the step's masked sonar), or both
        worked out now.
        """
        heard, self._heard = self._heard, None
        if heard is not None and heard[0] == t_s:
            _, view, localised = heard
            return view, observation.with_odometry(localised.odometry)
        view = self._listen(peers, flags, t_s)
        return view, self._localise(observation, view, peers, t_s)

    def _listen(self, peers: Mapping[str, PeerState], flags: Flags | None, t_s: float) -> FleetView:
        """Leadership from the flags; join once anyone is heard; followers take the
        group's progress from the leader; whom to track, and its state if fresh.
        """
        lsh = self.leadership
        live = lsh.live(flags if flags is not None else peers, t_s)
        was_leader = lsh.is_leader
        change = lsh.update(live, t_s)
        is_leader = lsh.is_leader
        others = len(live) - (self.robot_id in live)
        if others or self.parts.startup.waited_s(t_s) >= self.scenario.leadership.join_timeout_s:
            self.joined = True
        leader_flags = live.get(lsh.leader_id)
        if not is_leader and leader_flags is not None:
            self.parts.progress.copy_from(leader_flags)
            self.parts.keeper.copy_from(leader_flags)
        self.parts.apply_shape()
        self.parent_id = lsh.tracked(live)
        timeout_s = self.scenario.leader_timeout_s
        lead = _fresh(peers, self.parent_id, t_s, timeout_s)
        head = None
        if lead is not None and lsh.leader_id != self.parent_id:
            head = _fresh(peers, lsh.leader_id, t_s, timeout_s)
        if change is not None:
            self.role_reason = f"{change.reason} (epoch {change.epoch}, leader {change.leader_id})"
        took = change if is_leader and not was_leader else None
        lead_now, head_now = now(lead, t_s), now(head, t_s)
        anchor, anchor_now = (head, head_now) if head is not None else (lead, lead_now)
        slot = None
        if anchor is not None and anchor_now is not None:
            slot = self.parts.shape.slot_target(anchor, anchor_now)
        return FleetView(
            live, took, is_leader, lsh.leader_id, self.parent_id, lead, head,
            lead_now, head_now, slot,
        )  # fmt: skip

    def _localise(
        self, observation: Observation, view: FleetView, peers: Mapping[str, PeerState], t_s: float
    ) -> Observation:
        """The observation with the pose estimate in place of the odometry pose (and its
        covariance kept for the state), when the estimator is on; as it came otherwise.
        """
        if self.estimator is None:
            return observation
        odometry = observation.odometry
        anchors = {}
        if observation.relative:
            timeout_s = self.scenario.leader_timeout_s
            anchors = self.landmarks.pick(peers, view.leader_id, t_s=t_s, max_age_s=timeout_s)
        estimate = self.estimator.step(
            odometry, fixes=observation.fixes, relative=observation.relative, anchors=anchors
        )
        self._cov = estimate.cov
        return replace(
            observation, odometry=Odometry(estimate.pose, odometry.twist, odometry.stamp_s)
        )

    def _estimate(
        self, observation: Observation, sensing: Sensing, view: FleetView, t_s: float
    ) -> None:
        """Move the memories on: the leader's waypoints (an operator's goal in place of
        those not reached yet), how long each way has been blocked, who stopped for an
        obstacle, the path crossed, the active behaviour's progress (ground backed over,
        angle turned).
        """
        parts, odometry, operator = self.parts, observation.odometry, observation.operator
        if view.is_leader:
            if operator is not None and operator.goal is not None:
                parts.take_goal(operator.goal)
            parts.advance_waypoints(odometry.pose)
            parts.weigh_shapes(odometry.pose, t_s, navigating=self.fsm.state == State.NAVIGATE)
        parts.blocked.update(sensing.blocked, self.dt_s)
        reversing = self.fsm.state == State.DEADLOCK_REVERSE
        parts.stops.update(view.live, self.robot_id, reversing=reversing)
        if odometry.twist.v_mps > STANDSTILL_MPS:
            parts.course.crumbs.drop(odometry.pose.position)  # ground just crossed: free
        if parts.trail is not None and view.anchor is not None and not view.is_leader:
            parts.trail.hear(view.anchor.robot_id, view.anchor.pose.position, view.anchor.v_mps)
        if self._last_odometry is not None:
            self._active.observe(odometry, self._last_odometry)

    # --- decide ----------------------------------------------------------------------

    def _context(
        self,
        observation: Observation,
        sensing: Sensing,
        view: FleetView,
        stance: Stance,
        t_s: float,
        operator: Twist2D | None = None,
    ) -> StackContext:
        """What the guards read this step (built once, never written afterwards);
        `operator`: the twist an operator drives the robot with (None: none does).
        """
        parts, live, lead = self.parts, view.live, view.lead
        odometry = observation.odometry
        head = live.get(view.leader_id)
        progress, deadlock_cfg = parts.progress, self.scenario.deadlock
        reason = ""
        if view.is_leader:
            # A scripted leader (the paper's runs) keeps the paper's rule: all blocked.
            reason = group_deadlock(
                live,
                self.robot_id,
                confirm_s=self.scenario.navigation.confirm_s,
                widened=parts.plan != "scripted",
                queued=parts.shape.queued,
            )
        waypoints = parts.route.waypoints
        in_estop = stance.state == State.EMERGENCY_STOP
        return StackContext(
            is_leader=view.is_leader,
            plan=parts.plan,
            arrived=parts.plan == "goto" and progress.waypoint >= len(waypoints),
            role_reason=self.role_reason,
            joined=self.joined,
            reactive=self.scenario.navigation.reactive,
            bumper=sensing.bumper,
            imminent=sensing.imminent,
            standstill=abs(odometry.twist.v_mps) < STANDSTILL_MPS,
            way_clear=not in_estop or way_clear(sensing, parts.shape, view, odometry.pose),
            blocked_s=parts.blocked.of(stance.direction),
            way_free_s=parts.avoid.way_free_s,
            leader_lost=self.leadership.leader_lost(live),
            leader_blocked=head is not None and head.obstacle and not view.is_leader,
            leader_state=head.fsm_state if head is not None else "",
            parent_fresh=lead is not None,
            parent_v_mps=lead.v_mps if lead else 0.0,
            parent_direction=lead.direction if lead else 1,
            deadlock=bool(reason),
            deadlock_reason=reason,
            someone_stopped=parts.stops.someone_stopped(live, self.robot_id),
            retries_left=parts.retries_left(odometry.pose, deadlocked=bool(reason)),
            stuck_reason=(  # (read only in a deadlock: no text to format otherwise)
                f"{reason}; {progress.deadlocks} deadlock reverses already at waypoint "
                f"{progress.waypoint} (deadlock.max_retries = {deadlock_cfg.max_retries})"
                f"{'' if parts.planner.map is None else ' and no way to it on the map'}"
                if reason
                else ""
            ),
            reversed_m=parts.reverse.reversed_m,
            safe_distance_m=deadlock_cfg.safe_distance_m,
            path_used_up=parts.reverse.path_used_up,
            turned=parts.turn.turned,
            reshape_wanted=parts.keeper.reshape_wanted,
            reshaped=parts.reshape.reshaped,
            confirm_s=self.scenario.navigation.confirm_s,
            threshold_mps=self.scenario.controller.reverse_threshold_mps,
            others_busy=len(live.busy) > (self.robot_id in live.busy),
            operator=operator is not None,
            operator_clear=operator is None
            or operator.v_mps == 0.0
            or clear_towards(sensing, parts.shape, backwards=operator.v_mps < 0.0),
            **self._robot_condition(observation.status, stance.state),
        )

    def _robot_condition(self, status: RobotStatus, state: str) -> dict[str, Any]:
        """The robot's own stops, from its driver's status (the battery with a little
        hysteresis, so a voltage sagging about the mark does not toggle the state).
        """
        low_v, battery_v = self.robot.battery_low_v, status.battery_v
        battery_low = False
        if low_v is not None and battery_v is not None:
            margin_v = BATTERY_HYSTERESIS_V if state == State.LOW_BATTERY else 0.0
            battery_low = battery_v < low_v + margin_v
        return {
            "estopped": status.estopped,
            "faults": status.faults,
            "stalled": status.stalled,
            "battery_low": battery_low,
            "battery_v": battery_v,
        }

    def _enter(self, event: TransitionEvent, moment: Moment) -> None:
        """Exit and entry actions of a transition."""
        parts = self.parts
        parts.behaviours[event.source].leave(moment)
        if event.target in OUT_OF_FORMATION:
            self.formed = False
        parts.behaviours[event.target].enter(moment)
        if event.target not in (State.NAVIGATE, State.WANDER, State.AVOID):
            parts.steering.reset()
            parts.planner.forget_carrot()
        parts.senses.stall.reset()
        if event.target == State.DEADLOCK_REVERSE:
            parts.stops.reverse_begins(moment.view.live)

    # --- after the command ------------------------------------------------------------

    def _update_formed(self, pose: Pose2D, view: FleetView) -> None:
        state, lead = self.fsm.state, view.anchor
        if view.is_leader and state not in OUT_OF_FORMATION:
            self.formed = True
        elif state in OUT_OF_FORMATION:
            self.formed = False
        elif not self.formed and lead is not None and state != State.HOLD:
            target = self.parts.track.target(view)
            if target is None:
                return
            error_m = (pose.position - target.position).norm()
            error_rad = abs(wrap_angle(pose.theta_rad - target.theta_rad))
            within_m = self.parts.shape.formed_within_m(lead.robot_id, self.scenario.leadership)
            self.formed = error_m < within_m and error_rad < FORMED_RAD

    def _output(
        self,
        odometry: Odometry,
        command: Twist2D,
        sensing: Sensing,
        view: FleetView,
        event: TransitionEvent | None,
        t_s: float,
    ) -> StepOutput:
        # The published twist is the command being executed from t_s on: a follower that
        # dead-reckons over the state's age then lands where the leader really is.
        self._seq += 1
        pose, direction, progress = odometry.pose, self.direction, self.parts.progress
        # Stopped, the way it was going: the side its obstacle is on.
        way = self.parts.estop.way if self.fsm.state == State.EMERGENCY_STOP else direction
        state = PeerState(
            robot_id=self.robot_id,
            seq=self._seq,
            stamp_s=t_s,
            x_m=pose.x_m,
            y_m=pose.y_m,
            theta_rad=pose.theta_rad,
            v_mps=command.v_mps,
            omega_radps=command.omega_radps,
            fsm_state=self.state_name,
            obstacle=sensing.blocked[direction],
            direction=1 if way > 0 else -1,
            leader_id=self.parent_id or "",
            epoch=self.leadership.epoch,
            formation_leader_id=self.leadership.leader_id,
            clear=sensing.path_clear,
            formed=self.formed,
            blocked_s=self.parts.blocked.of(direction),
            dead_end=sensing.dead_end,
            waypoint=progress.waypoint,
            deadlocks=progress.deadlocks,
            profile_s=progress.profile_s,
            cov=self._cov,
            shape_source=self.parts.keeper.key.source,
            shape_target=self.parts.keeper.key.target,
            morph=self.parts.keeper.key.morph,
            settled=self.fsm.state == State.FORMATION_TRACK and self.parts.track.settled,
            shape_fits=self.parts.keeper.scenario_fits,
        )
        return StepOutput(
            command,
            state,
            (event,) if event else (),
            view.took,
            self.limiter.saturations,
            self.limiter.accel_limited,
            self.parts.planner.scan,
        )


def _operator_twist(observation: Observation, t_s: float) -> Twist2D | None:
    """The twist an operator drives the robot with at `t_s` (None: none young enough)."""
    operator = observation.operator
    if operator is None or not operator.drives(t_s):
        return None
    return operator.twist


def _fresh(
    peers: Mapping[str, PeerState], rid: str | None, t_s: float, timeout_s: float
) -> PeerState | None:
    """`rid`'s state, unless it is older than `timeout_s` at `t_s` (or there is none)."""
    state = peers.get(rid) if rid else None
    if state is None or t_s - state.stamp_s > timeout_s:
        return None
    return state
