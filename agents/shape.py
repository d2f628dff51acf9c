"""The formation's shape as one robot sees it: every other robot's slot in its frame
(fixed, for a rigid shape), how far the shape reaches, how fast it may turn, where this
robot's slot is behind the robot it tracks, and the free way of the whole shape.
"""

from __future__ import annotations

import math

import numpy as np

from phalanx.agents.behaviours.navigation import Clearances, turn_rate_radps
from phalanx.agents.leadership import Flags
from phalanx.agents.perception import (
    HEADINGS_RAD,
    FloatArray,
    braking_gap_m,
    corridor_clearance,
    nearest_m,
)
from phalanx.core.config import NavigationConfig
from phalanx.core.formation import Formation
from phalanx.core.geometry import Pose2D, Twist2D, Vec2
from phalanx.core.limits import KinematicLimits
from phalanx.core.peers import PeerState
from phalanx.core.rigid_body import predict_leader, rigid_body_target
from phalanx.core.states import OUT_OF_FORMATION

Points = tuple[FloatArray, FloatArray]
# Room beyond the swept disc a turn on the spot needs (m).
SWEEP_MARGIN_M = 0.35
# Left and right, for the formation's room to either side.
SIDEWAYS_RAD = np.array([math.pi / 2, -math.pi / 2])


class Shape:
    """One robot's view of its formation's shape (SI units, this robot's body frame)."""

    def __init__(
        self,
        robot_id: str,
        formation: Formation,
        *,
        radius_m: float,
        nav: NavigationConfig,
        limits: KinematicLimits,
        dt_s: float,
    ) -> None:
        self.robot_id = robot_id
        self.formation = formation
        self.radius_m = radius_m
        self.nav = nav
        self.limits = limits
        self.dt_s = dt_s
        here = formation.positions[robot_id]
        self.offsets = {r: p - here for r, p in formation.positions.items()}
        self.follower_slots = [p for r, p in self.offsets.items() if r != robot_id]
        # How far the shape reaches from this robot (what turning on the spot sweeps).
        self.reach_m = max((o.norm() for o in self.offsets.values()), default=0.0)
        ys = [p.y_m for p in formation.positions.values()]
        # Half the shape's width across its heading, plus a robot radius.
        self.half_span_m = (max(ys) - min(ys)) / 2 + radius_m
        self.half_width_m = radius_m + nav.body_margin_m

    def turn_rate_radps(self) -> float:
        """The fastest turn on the spot that keeps every slot within its speed share."""
        return turn_rate_radps(
            self.follower_slots, self.limits.v_max_mps, self.limits.omega_max_radps
        )

    def stop_gap_m(self) -> float:
        """The gap a robot at cruise speed needs to stop in, margin included (m)."""
        braking = braking_gap_m(
            self.nav.cruise_mps, decel_mps2=self.limits.decel_mps2, latency_s=2 * self.dt_s
        )
        return braking + self.nav.stop_margin_m

    def sweep_clear(self, points: Points) -> bool:
        """Whether the shape can turn on the spot about this robot: nothing within the
        disc its slots sweep (seen from here).
        """
        return nearest_m(points) > self.reach_m + self.radius_m + SWEEP_MARGIN_M

    def slots_in_formation(self, live: Flags, *, origin: bool = False) -> list[Vec2]:
        """Slots of the robots in formation, in this robot's frame (own origin if asked)."""
        slots = [Vec2(0.0, 0.0)] if origin else []
        for rid, f in live.items():
            if rid != self.robot_id and f.formed and f.fsm_state not in OUT_OF_FORMATION:
                slots.append(self.offsets[rid])
        return slots

    def clearances(self, points: Points, live: Flags, *, whole_shape: bool) -> Clearances:
        """Free way along every candidate heading: own, and (`whole_shape`: a navigating
        leader) the whole formation's, with its room to either side.
        """
        narrow = corridor_clearance(points, HEADINGS_RAD, half_width_m=self.half_width_m)
        if not whole_shape:
            return Clearances(narrow, narrow)
        slots = self.slots_in_formation(live, origin=True)
        wide = corridor_clearance(
            points, HEADINGS_RAD, half_width_m=self.half_width_m, origins=slots
        )
        left, right = corridor_clearance(
            points, SIDEWAYS_RAD, half_width_m=self.half_width_m, origins=slots, turning=False
        )
        return Clearances(wide, narrow, float(left), float(right))

    def slot_target(self, lead: PeerState, t_s: float) -> tuple[Pose2D, Twist2D]:
        """The robot's slot behind `lead`, moving rigidly with it: the target pose and its
        feed-forward twist, the leader's state dead-reckoned over its age to `t_s`.
        """
        age_s = max(0.0, t_s - lead.stamp_s)
        leader = predict_leader(lead.pose, lead.twist, age_s)
        slot = self.formation.slot_of(self.robot_id, lead.robot_id)
        return rigid_body_target(leader, lead.twist, slot)
