"""Follower behaviours: tracking the slot behind the robot it follows, forwards and in
reverse (the formation layer), and going round an obstacle that blocks only this robot
(`AVOID`, the navigation layer's part in a follower).
"""

from __future__ import annotations

import math

from phalanx.agents.behaviours.base import Behaviour, Moment
from phalanx.agents.behaviours.navigation import Clearances, bearing_rad, steer
from phalanx.agents.control.common import FollowerController, FollowerInput
from phalanx.agents.memory import Steering
from phalanx.agents.perception import HEADINGS_RAD, clearance_along, corridor_clearance
from phalanx.agents.shape import Shape
from phalanx.core.config import Scenario
from phalanx.core.geometry import ZERO_TWIST, Pose2D, Twist2D, Vec2, wrap_angle
from phalanx.core.limits import KinematicLimits
from phalanx.core.peers import PeerState
from phalanx.core.states import State

# A follower on its slot aligns its heading once its leader has stood still this long
# (below these speeds), turning at this gain.
ALIGN_AFTER_S = 1.0
STILL_MPS = 0.005
STILL_RADPS = 0.005
ALIGN_GAIN_PER_S = 1.0
# A follower going round an obstacle aims this far ahead of its moving slot.
AVOID_LEAD_S = 1.0


class Track(Behaviour):
    """FORMATION_TRACK and FORMATION_REVERSE: the follower controller on the slot behind
    the tracked robot, its control point ahead of the axle forwards and behind it in
    reverse (the paper's switch, figure 4a, is the state; one object serves both, so
    how long the leader has stood still carries across the switch).
    """

    def __init__(
        self,
        robot_id: str,
        scenario: Scenario,
        *,
        shape: Shape,
        limits: KinematicLimits,
        controller: FollowerController,
    ) -> None:
        self.robot_id = robot_id
        self.shape, self.limits, self.controller = shape, limits, controller
        self.dt_s = scenario.dt_s
        self.formed_m = scenario.leadership.formed_m
        self.leader_still_s = 0.0

    def command(self, moment: Moment) -> Twist2D:
        """The controller's twist, or a turn on the spot onto the slot's heading."""
        lead = moment.view.anchor
        if lead is None:
            return ZERO_TWIST
        still = abs(lead.v_mps) < STILL_MPS and abs(lead.omega_radps) < STILL_RADPS
        self.leader_still_s = self.leader_still_s + self.dt_s if still else 0.0
        if self.leader_still_s >= ALIGN_AFTER_S:
            aligned = self._align(moment.pose, lead, moment.t_s)
            if aligned is not None:
                return aligned
        odometry = moment.odometry
        inp = FollowerInput(
            follower=odometry.pose,
            follower_twist=odometry.twist,
            leader=lead.pose,
            leader_twist=lead.twist,
            leader_age_s=max(0.0, moment.t_s - lead.stamp_s),
            slot=self.shape.formation.slot_of(self.robot_id, lead.robot_id),
            direction=-1 if moment.state == State.FORMATION_REVERSE else 1,
            dt_s=self.dt_s,
        )
        return self.controller.command(inp)

    def _align(self, pose: Pose2D, lead: PeerState, t_s: float) -> Twist2D | None:
        """On its slot beside a leader standing still, turn on the spot to the slot's heading.

        Tracking a point aims the robot's position, not its heading, and a still target
        leaves any heading error where it is: the group's next move, a reverse out of a
        dead end say, would start with it.
        """
        target, _ = self.shape.slot_target(lead, t_s)
        if (pose.position - target.position).norm() > self.formed_m:
            return None
        error = wrap_angle(target.theta_rad - pose.theta_rad)
        rate = min(self.limits.omega_max_radps, ALIGN_GAIN_PER_S * abs(error))
        return Twist2D(0.0, math.copysign(rate, error))


class Avoid(Behaviour):
    """AVOID: off the slot, round the obstacle towards a point a little ahead of the
    moving slot; `way_free_s` says how long the way back has been free (a guard ends
    the detour on it).
    """

    def __init__(
        self,
        scenario: Scenario,
        *,
        shape: Shape,
        limits: KinematicLimits,
        steering: Steering,
    ) -> None:
        self.nav = scenario.navigation
        self.dt_s = scenario.dt_s
        self.shape, self.limits, self.steering = shape, limits, steering
        self.way_free_s = 0.0

    def enter(self, moment: Moment) -> None:
        """A new detour: the way back has not been free yet."""
        self.way_free_s = 0.0

    def command(self, moment: Moment) -> Twist2D:
        """Steer round what blocks the way to the slot."""
        lead = moment.view.anchor
        if lead is None:
            return ZERO_TWIST
        pose, sensing = moment.pose, moment.sensing
        target, ff = self.shape.slot_target(lead, moment.t_s)
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
        twist, chosen = steer(
            desired,
            Clearances(narrow, narrow),
            nav=self.nav,
            speed_mps=speed,
            stop_gap_m=self.shape.stop_gap_m(),
            need_m=min(dist_m, self.nav.lookahead_m),
            omega_max_radps=self.limits.omega_max_radps,
            previous_rad=previous,
        )
        self.steering.chosen_rad = pose.theta_rad + chosen
        return twist
