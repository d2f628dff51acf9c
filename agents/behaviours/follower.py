"""Follower behaviours: tracking the slot behind the robot it follows, forwards and in
reverse (the formation layer), and going round an obstacle that blocks only this robot
(`AVOID`, the navigation layer's part in a follower).
"""

from __future__ import annotations

import math

from phalanx.agents.behaviours.base import Behaviour, Moment, turn_on_spot
from phalanx.agents.control.common import FollowerController, FollowerInput
from phalanx.agents.inputs import FleetView
from phalanx.agents.navigation import (
    HEADINGS_RAD,
    Clearances,
    Steering,
    Trail,
    bearing_rad,
    clearance_along,
    corridor_clearance,
    steer,
)
from phalanx.agents.shape import Shape
from phalanx.core.config import NavigationConfig
from phalanx.core.geometry import ZERO_TWIST, Pose2D, Twist2D, Vec2, wrap_angle
from phalanx.core.limits import KinematicLimits
from phalanx.core.states import DEADLOCK_STATES, State

# A follower near its slot settles onto it once its leader has stood still this long
# (below these speeds): it drives straight onto the slot's position (within SETTLE_M of
# it), then turns on the spot to the slot's heading, turning at this gain.
ALIGN_AFTER_S = 1.0
STILL_MPS = 0.005
STILL_RADPS = 0.005
ALIGN_GAIN_PER_S = 3.0
SETTLE_M = 0.5  # further off, the controller brings it back
# Near enough: only the heading is left; it drives again only once this far off (a pose
# estimate's jitter does not send it turning back and forth). A reverse starts from
# here, and the controller takes an offset out over seconds (its heading mode decays
# with control_point_m / |v|, 2 s at reverse speed): 1 cm left a column of five's rear
# robots 0.73 deg off the robot they track 5 s into its reverse, 5 mm 0.33 deg.
ON_SLOT_M, OFF_SLOT_M = 0.005, 0.03
# On its slot and this near the slot's heading, it has settled (`Track.settled`): a leader
# pausing before a deadlock reverse backs off once every follower has (the reverse's
# errors start from these: its bound on the heading is 0.5 deg).
SETTLED_RAD = math.radians(0.5)
SETTLE_GAIN_PER_S = 2.0  # heading gain on the way to the slot's position
SETTLE_SPEED_MPS = (0.02, 0.1)  # slowest, fastest on the way
SETTLE_AIMED_RAD = math.radians(10.0)  # drives only once aimed this well
# While the group is in one of these states, a column's follower keeps to its rigid
# slot (`_keeps_to_path`).
RIGID_STATES = DEADLOCK_STATES | {State.ARRIVED}
# A follower going round an obstacle aims this far ahead of its moving slot.
AVOID_LEAD_S = 1.0
# A follower boxed in on its detour (its way blocked at the bumper) takes any way out
# with room for this many body widths and a stop.
POCKET_NEED_BODIES = 1.0


class Track(Behaviour):
    """FORMATION_TRACK and FORMATION_REVERSE: the follower controller on the slot behind
    the tracked robot, its control point ahead of the axle forwards and behind it in
    reverse (the paper's switch, figure 4a, is the state; one object serves both, so
    how long the leader has stood still carries across the switch). Given the tracked
    robot's `trail`, a column's follower keeps forwards to its slot on that robot's path.
    """

    def __init__(
        self,
        robot_id: str,
        *,
        dt_s: float,
        shape: Shape,
        limits: KinematicLimits,
        controller: FollowerController,
        trail: Trail | None = None,
    ) -> None:
        self.robot_id = robot_id
        self.shape, self.limits, self.controller = shape, limits, controller
        self.trail = trail
        self.dt_s = dt_s
        self.leader_still_s = 0.0
        self.on_slot = False  # settled onto the slot's position while the leader stands
        self.settled = False  # ... and turned to the slot's heading (this step)

    def command(self, moment: Moment) -> Twist2D:
        """The controller's twist, or (its leader standing still) settling onto the slot."""
        self.settled = False
        view = moment.view
        lead, rigid = view.anchor, _rigid(view)
        if lead is None or rigid is None:
            return ZERO_TWIST
        still = abs(lead.v_mps) < STILL_MPS and abs(lead.omega_radps) < STILL_RADPS
        self.leader_still_s = self.leader_still_s + self.dt_s if still else 0.0
        self.on_slot = self.on_slot and still
        on_path = self.path_slot(view) if _keeps_to_path(moment) else None
        if self.leader_still_s >= ALIGN_AFTER_S:
            settling = self._settle(moment.pose, on_path or rigid)
            if settling is not None:
                return settling
        odometry = moment.odometry
        slot = self.shape.formation.slot_of(self.robot_id, lead.robot_id)
        leader, twist, age_s = lead.pose, lead.twist, max(0.0, moment.t_s - lead.stamp_s)
        leader_now, target = view.anchor_now, view.slot  # (the slot laid out from it)
        if on_path is not None:
            # The robot that would have this slot there, driving straight on.
            at = on_path.to_world(Vec2(-slot.x_m, -slot.y_m))
            leader, age_s = Pose2D(at.x_m, at.y_m, on_path.theta_rad), 0.0
            leader_now, twist, target = leader, Twist2D(lead.v_mps, 0.0), None
        inp = FollowerInput(
            follower=odometry.pose,
            follower_twist=odometry.twist,
            leader=leader,
            leader_twist=twist,
            leader_age_s=age_s,
            slot=slot,
            direction=-1 if moment.state == State.FORMATION_REVERSE else 1,
            dt_s=self.dt_s,
            leader_now=leader_now,
            target=target,
        )
        return self.controller.command(inp)

    def path_slot(self, view: FleetView) -> Pose2D | None:
        """The robot's slot on its anchor's path: None without a trail of it, for a slot
        not straight behind it, or while the path is shorter than the slot is far.
        """
        lead, trail = view.anchor, self.trail
        if lead is None or view.anchor_now is None:
            return None
        if trail is None or trail.robot_id != lead.robot_id:
            return None
        behind_m = self.shape.behind_by_m(lead.robot_id)
        if behind_m is None:
            return None
        return trail.pose_back(view.anchor_now.position, behind_m)

    def target(self, view: FleetView) -> Pose2D | None:
        """Where this robot belongs now: its slot on its anchor's path, or the rigid
        slot (None without an anchor).
        """
        return self.path_slot(view) or _rigid(view)

    def _settle(self, pose: Pose2D, target: Pose2D) -> Twist2D | None:
        """Near its slot beside a leader standing still: drive straight onto the slot's
        position (forwards or backwards, whichever needs less turning), then turn on the
        spot to the slot's heading. None further off than `SETTLE_M`.

        Tracking a point aims a point ahead of (or behind) the axle, not the axle and the
        heading: beside a still target it ends with the axle off the slot by up to that
        distance and the heading off by up to 90 deg, which the group's next move, a
        reverse out of a dead end say, would start with. A differential drive reaches a
        pose standing still only this way (turn, drive, turn).
        """
        offset = target.position - pose.position
        distance_m = offset.norm()
        if distance_m > SETTLE_M:
            return None
        self.on_slot = distance_m <= (OFF_SLOT_M if self.on_slot else ON_SLOT_M)
        if self.on_slot:
            heading_error = wrap_angle(target.theta_rad - pose.theta_rad)
            self.settled = abs(heading_error) <= SETTLED_RAD
            return turn_on_spot(heading_error, ALIGN_GAIN_PER_S, self.limits.omega_max_radps)
        error = wrap_angle(math.atan2(offset.y_m, offset.x_m) - pose.theta_rad)
        sign = 1.0
        if abs(error) > math.pi / 2:  # backing onto it turns less
            sign, error = -1.0, wrap_angle(error + math.pi)
        turn = turn_on_spot(error, SETTLE_GAIN_PER_S, self.limits.omega_max_radps)
        if abs(error) > SETTLE_AIMED_RAD:
            return turn
        slow, fast = SETTLE_SPEED_MPS
        speed = min(fast, max(slow, ALIGN_GAIN_PER_S * distance_m)) * math.cos(error)
        return Twist2D(sign * min(speed, distance_m / self.dt_s), turn.omega_radps)


def _rigid(view: FleetView) -> Pose2D | None:
    """The rigid slot's target pose in `view` (None without an anchor)."""
    return None if view.slot is None else view.slot[0]


def _keeps_to_path(moment: Moment) -> bool:
    """Whether a column's follower keeps to the path driven ahead of it: tracking
    forwards, but for while the group backs out of a deadlock (a rigid turn and
    reverse, which start from the rigid shape) or stands at its goal.
    """
    if moment.state != State.FORMATION_TRACK:
        return False
    head = moment.view.live.get(moment.view.leader_id)
    return head is None or head.fsm_state not in RIGID_STATES


class Avoid(Behaviour):
    """AVOID: off the slot, round the obstacle towards a point a little ahead of the
    moving slot; `way_free_s` says how long the way back has been free (a guard ends
    the detour on it).
    """

    def __init__(
        self,
        nav: NavigationConfig,
        *,
        dt_s: float,
        shape: Shape,
        limits: KinematicLimits,
        steering: Steering,
    ) -> None:
        self.nav = nav
        self.dt_s = dt_s
        self.shape, self.limits, self.steering = shape, limits, steering
        self.way_free_s = 0.0

    def enter(self, moment: Moment) -> None:
        """A new detour: the way back has not been free yet."""
        self.way_free_s = 0.0

    def command(self, moment: Moment) -> Twist2D:
        """Steer round what blocks the way to the slot."""
        if moment.view.slot is None:
            return ZERO_TWIST
        pose, sensing = moment.pose, moment.sensing
        target, ff = moment.view.slot
        lead_m = ff.v_mps * AVOID_LEAD_S
        aim = target.position + Vec2(
            lead_m * math.cos(target.theta_rad), lead_m * math.sin(target.theta_rad)
        )
        desired, dist_m = bearing_rad(pose, aim), (aim - pose.position).norm()
        half_width = self.shape.half_width_m
        way_m = clearance_along(sensing.points, desired, half_width_m=half_width)
        free = way_m >= min(dist_m, self.nav.clear_range_m) and not sensing.blocked[1]
        self.way_free_s = self.way_free_s + self.dt_s if free else 0.0
        speed = min(0.9 * self.limits.v_max_mps, 0.5 * dist_m + abs(ff.v_mps))
        narrow = corridor_clearance(sensing.points, HEADINGS_RAD, half_width_m=half_width)
        chosen_rad = self.steering.chosen_rad
        previous = None if chosen_rad is None else wrap_angle(chosen_rad - pose.theta_rad)
        clear, stop_gap_m = Clearances(narrow, narrow), self.shape.stop_gap_m()

        def steer_for(need_m: float, window_rad: float) -> tuple[Twist2D, float]:
            return steer(
                desired,
                clear,
                nav=self.nav,
                speed_mps=speed,
                stop_gap_m=stop_gap_m,
                need_m=need_m,
                omega_max_radps=self.limits.omega_max_radps,
                window_rad=window_rad,
                previous_rad=previous,
            )

        twist, chosen = steer_for(min(dist_m, self.nav.lookahead_m), math.pi / 2)
        if clear.along_m(chosen) <= stop_gap_m:
            # In a pocket: no way within a quarter turn of the aim is clear for the
            # whole way, and what it heads for is at its bumper. A lone robot may turn
            # its back on its slot: the way nearest the aim with room for a body
            # width and a stop, all round.
            twist, chosen = steer_for(POCKET_NEED_BODIES * 2 * half_width + stop_gap_m, math.pi)
        self.steering.chosen_rad = pose.theta_rad + chosen
        return twist
