"""The formation's shape as one robot sees it: every other robot's slot in its frame
(fixed, for a rigid shape), how far the shape reaches, how fast it may turn, where this
robot's slot is behind the robot it tracks, and the free way of the whole shape.
"""

from __future__ import annotations

import math
from functools import cached_property

import numpy as np

from phalanx.agents.leadership import Flags
from phalanx.agents.navigation import (
    HEADINGS_RAD,
    Clearances,
    corridor_clearance,
    turn_rate_radps,
)
from phalanx.agents.perception import FloatArray, braking_gap_m, nearest_m
from phalanx.core.config import LeadershipConfig, NavigationConfig
from phalanx.core.formation import Formation
from phalanx.core.geometry import Pose2D, Twist2D, Vec2
from phalanx.core.limits import KinematicLimits
from phalanx.core.peers import PeerState
from phalanx.core.rigid_body import rigid_body_target
from phalanx.core.states import OUT_OF_FORMATION

Points = tuple[FloatArray, FloatArray]
# Room beyond the swept disc a turn on the spot needs (m).
SWEEP_MARGIN_M = 0.35
# A navigating leader turns about a point at least this much beyond the shape's furthest
# slot across its heading (m): no slot of the shape is then swung backwards.
TURN_CENTRE_MARGIN_M = 0.75
# ... and on an arc no tighter than this share of the shape's reach from it.
TAIL_SHARE = 0.5
# A slot at most this far across its tracked robot's heading, behind it, trails it (m).
TRAIL_ACROSS_M = 1e-6
# Left and right, for the formation's room to either side.
SIDEWAYS_RAD = np.array([math.pi / 2, -math.pi / 2])


_LAST_FORMATION: list[tuple[Formation, tuple[str, ...], FloatArray, FloatArray]] = []


def _slot_arrays(formation: Formation) -> tuple[tuple[str, ...], FloatArray, FloatArray]:
    """Robot ids and slot positions of `formation` as arrays (the last one's kept: a fleet
    builds all its robots' shapes from one formation).
    """
    last = _LAST_FORMATION[0] if _LAST_FORMATION else None
    if last is None or last[0] is not formation:
        ids = tuple(formation.positions)
        xs = np.array([p.x_m for p in formation.positions.values()], dtype=np.float64)
        ys = np.array([p.y_m for p in formation.positions.values()], dtype=np.float64)
        last = (formation, ids, xs, ys)
        _LAST_FORMATION[:] = [last]
    return last[1], last[2], last[3]


def _furthest_m(dx: FloatArray, dy: FloatArray) -> float:
    """The largest `Vec2.norm` of the offsets (0 if none): math.hypot on the few that
    numpy's hypot puts within rounding of the largest.
    """
    if dx.size == 0:
        return 0.0
    rough = np.hypot(dx, dy)
    near_top = np.flatnonzero(rough >= float(rough.max()) * (1.0 - 1e-9)).tolist()
    return max(math.hypot(float(dx[i]), float(dy[i])) for i in near_top)


def _behind(formation: Formation, robot_id: str, parent: str) -> bool:
    """Whether `robot_id`'s slot is straight behind `parent`'s."""
    slot = formation.slot_of(robot_id, parent)
    return slot.x_m < 0.0 and abs(slot.y_m) <= TRAIL_ACROSS_M


# What a shape derives from its slots once (dropped when it adopts new ones).
_CACHED = (
    "offsets", "other_slots", "follower_slots", "trailing", "queued", "reach_m", "whole_reach_m",
)  # fmt: skip


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
        self.radius_m = radius_m
        self.nav = nav
        self.limits = limits
        self.dt_s = dt_s
        self.adopt(formation)

    def adopt(self, formation: Formation) -> None:
        """Take `formation`'s slots (the group changed its shape; the same robots)."""
        self.formation = formation
        for cached in _CACHED:
            self.__dict__.pop(cached, None)
        here = formation.positions[self.robot_id]
        # Every slot less this one's, as arrays (a fleet of n builds n of these: O(n) each
        # in numpy, the same numbers as subtracting the Vec2s)
        self._ids, xs, ys = _slot_arrays(formation)
        self._dx, self._dy = xs - here.x_m, ys - here.y_m
        # Half the shape's width across its heading, plus a robot radius.
        self.half_span_m = (float(ys.max()) - float(ys.min())) / 2 + self.radius_m
        self.half_width_m = self.radius_m + self.nav.body_margin_m
        # How far the shape reaches across this robot's heading (either side).
        self.across_m = float(np.abs(self._dy).max()) if self._dy.size else 0.0

    @cached_property
    def offsets(self) -> dict[str, Vec2]:
        """Every robot's slot relative to this robot's (formation frame), this one's included."""
        dx, dy = self._dx.tolist(), self._dy.tolist()
        return {r: Vec2(x, y) for r, x, y in zip(self._ids, dx, dy, strict=True)}

    @cached_property
    def trailing(self) -> frozenset[str]:
        """The robots that trail, with this robot leading: each tracks a slot straight
        behind a robot other than this one (a column's third robot on). This robot's
        turns and the whole shape's free way are reckoned without them: their slots
        still swing with its turns, but they catch up at their own speed limit, going
        round (`AVOID`) what lies across their way, instead of holding a long column to
        the turn rate and the straight course its tail's swing alone would allow.
        """
        formation = self.formation
        parents = formation.reroot(self.robot_id)
        return frozenset(
            r
            for r, parent in parents.items()
            if parent is not None and parent != self.robot_id and _behind(formation, r, parent)
        )

    @cached_property
    def queued(self) -> dict[str, str]:
        """Each robot whose slot is straight behind its parent's on the follow tree with
        this robot leading (a column), and that parent: the robot in its way.
        """
        formation = self.formation
        parents = formation.reroot(self.robot_id)
        return {
            r: parent
            for r, parent in parents.items()
            if parent is not None and _behind(formation, r, parent)
        }

    def behind_by_m(self, anchor_id: str) -> float | None:
        """How far this robot's slot is straight behind `anchor_id`'s (m), or None if it
        is not straight behind it (a column's follower, not a wedge's or a line's).
        """
        if not _behind(self.formation, self.robot_id, anchor_id):
            return None
        return -self.formation.slot_of(self.robot_id, anchor_id).x_m

    def formed_within_m(self, anchor_id: str, leadership: LeadershipConfig) -> float:
        """How near its slot, laid out from `anchor_id`'s, this robot is back in
        formation: `formed_m`, or `formed_share` of the slot's distance from it if more (a
        column's tail 4 m back moves 0.1 m sideways when the leader turns by 1.4 deg).
        """
        distance_m = self.formation.slot_of(self.robot_id, anchor_id).norm()
        return max(leadership.formed_m, leadership.formed_share * distance_m)

    @cached_property
    def whole_reach_m(self) -> float:
        """How far the whole shape reaches from this robot, trailing robots included."""
        return _furthest_m(self._dx, self._dy)

    @cached_property
    def reach_m(self) -> float:
        """How far the shape's robots that do not trail reach from this robot: what its
        turning on the spot is reckoned to sweep.
        """
        keep = [i for i, r in enumerate(self._ids) if r not in self.trailing]
        return _furthest_m(self._dx[keep], self._dy[keep])

    @cached_property
    def other_slots(self) -> dict[str, Vec2]:
        """Every other robot's slot relative to this robot's."""
        return {r: p for r, p in self.offsets.items() if r != self.robot_id}

    @cached_property
    def follower_slots(self) -> list[Vec2]:
        """Every other robot's slot relative to this robot's, but for those that trail."""
        return [p for r, p in self.other_slots.items() if r not in self.trailing]

    def slots_within(self, distance_m: float) -> dict[str, Vec2]:
        """The robots whose slot is nearer than `distance_m` to this robot's (by
        `Vec2.norm`; this one included), in the formation's order.
        """
        rough = np.hypot(self._dx, self._dy)  # (a hair wide: exact test below)
        out = {}
        for i in np.flatnonzero(rough < distance_m * (1.0 + 1e-9) + 1e-12).tolist():
            offset = Vec2(float(self._dx[i]), float(self._dy[i]))
            if offset.norm() < distance_m:
                out[self._ids[i]] = offset
        return out

    def turn_rate_radps(self, *, rigid: bool = False) -> float:
        """The fastest turn on the spot that keeps every slot within its speed share:
        the slots that do not trail, or (`rigid`: the deadlock's turns, which swing the
        whole shape round as one body before it backs out) every slot.
        """
        slots = list(self.other_slots.values()) if rigid else self.follower_slots
        return turn_rate_radps(slots, self.limits.v_max_mps, self.limits.omega_max_radps)

    def turn_radius_m(self) -> float:
        """The tightest arc this robot may lead the shape along (m): the configured
        `min_turn_radius_m`, or less for a short shape narrow across its heading (a
        short column follows its leader round a tight bend; a wide line abreast cannot,
        and a long column's tail would sweep wide of the leader's path).
        """
        across = self.across_m + self.radius_m + TURN_CENTRE_MARGIN_M
        return min(self.nav.min_turn_radius_m, max(across, TAIL_SHARE * self.reach_m))

    def stop_gap_m(self) -> float:
        """The gap a robot at cruise speed needs to stop in, margin included (m)."""
        braking = braking_gap_m(
            self.nav.cruise_mps, decel_mps2=self.limits.decel_mps2, latency_s=2 * self.dt_s
        )
        return braking + self.nav.stop_margin_m

    def sweep_clear(self, points: Points, *, rigid: bool = False) -> bool:
        """Whether the shape can turn on the spot about this robot: nothing within the
        disc its slots sweep (seen from here): those that do not trail, or (`rigid`: the
        deadlock's question, whose turns swing the whole shape as one body) all of them.
        """
        reach_m = self.whole_reach_m if rigid else self.reach_m
        return nearest_m(points) > reach_m + self.radius_m + SWEEP_MARGIN_M

    def slots_in_formation(self, live: Flags, *, origin: bool = False) -> list[Vec2]:
        """Slots of the robots in formation that do not trail, in this robot's frame (own
        origin if asked).
        """
        slots = [Vec2(0.0, 0.0)] if origin else []
        trailing = self.trailing
        for rid, f in live.items():
            if rid == self.robot_id or rid in trailing:
                continue
            if f.formed and f.fsm_state not in OUT_OF_FORMATION:
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

    def slot_target(self, lead: PeerState, lead_now: Pose2D) -> tuple[Pose2D, Twist2D]:
        """The robot's slot behind `lead`, moving rigidly with it: the target pose and its
        feed-forward twist, with `lead` where it is now (`lead_now`, its state's pose
        dead-reckoned to the step's time: `phalanx.agents.inputs.now`).
        """
        slot = self.formation.slot_of(self.robot_id, lead.robot_id)
        return rigid_body_target(lead_now, lead.twist, slot)
