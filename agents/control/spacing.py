"""Keep apart: the last word on a command before the limiter, against robot contacts.

Every robot masks the formation's others out of its sonar (they are not obstacles to
avoid), so the sonar guards cannot stop two robots of the group from meeting; the
formation's geometry normally keeps them apart, but a group re-rooted by handovers and
reversing along bent tracks can fold onto itself. This filter reads where the others
said they were and caps the speed at which this robot closes on each of them.

The cap is a braking bound. Two robots at centre distance `d` have `gap = d - 2 r -
margin` of room; each takes half of it as its own, so this robot's speed towards the
other (`v cos(bearing)`) may not exceed the speed it can still brake from within half
the gap, after `latency_s` of reaction: the `u` with `u latency + u^2 / (2 decel)` equal
to `gap / 2`, the inverse of `braking_gap_m`. Turning is never limited: a round robot
turning on the spot closes on nobody, and turning away is how it gets out.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping

import numpy as np

from phalanx.agents.perception import braking_gap_m
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.peers import PeerState


def closing_speed_cap_mps(gap_m: float, *, decel_mps2: float, latency_s: float) -> float:
    """The highest speed (m/s, >= 0) from which a robot stops within `gap_m / 2` (its
    half of the room between two robots), reacting after `latency_s`.
    """
    share = max(0.0, gap_m) / 2.0
    a_l = decel_mps2 * latency_s
    return max(0.0, math.sqrt(a_l * a_l + 2.0 * decel_mps2 * share) - a_l)


def keep_apart(
    command: Twist2D,
    pose: Pose2D,
    peers: Mapping[str, PeerState],
    *,
    own_id: str,
    contact_m: float,
    decel_mps2: float,
    latency_s: float,
    near: Collection[str] | None = None,
) -> Twist2D:
    """`command` with its speed scaled down (never reversed) so that this robot closes on
    no other robot in `peers` (only those in `near`, if given) faster than it could brake
    within its share of the gap. `contact_m`: the centre distance (m) at which two robots
    count as too close.
    """
    v = command.v_mps
    if v == 0.0:
        return command
    heading_x, heading_y = math.cos(pose.theta_rad), math.sin(pose.theta_rad)
    limit = abs(v)
    for rid in peers if near is None else near:
        other = peers.get(rid)
        if other is None or rid == own_id:
            continue
        dx, dy = other.x_m - pose.x_m, other.y_m - pose.y_m
        d = math.hypot(dx, dy)
        towards = (heading_x * dx + heading_y * dy) / d if d > 0.0 else 1.0
        closing = towards if v > 0.0 else -towards  # the share of |v| spent closing in
        if closing <= 0.0:
            continue
        cap = closing_speed_cap_mps(d - contact_m, decel_mps2=decel_mps2, latency_s=latency_s)
        limit = min(limit, cap / closing)
    if limit >= abs(v):
        return command
    return Twist2D(math.copysign(limit, v), command.omega_radps)


class Spacing:
    """`keep_apart` with one robot's parameters, and how often it cut a command."""

    def __init__(
        self, robot_id: str, *, contact_m: float, decel_mps2: float, latency_s: float
    ) -> None:
        self.robot_id = robot_id
        self.contact_m, self.decel_mps2, self.latency_s = contact_m, decel_mps2, latency_s
        self.cuts = 0  # commands slowed down to keep apart
        self.cut = False  # whether the last command was

    def apply(
        self,
        command: Twist2D,
        pose: Pose2D,
        peers: Mapping[str, PeerState],
        near: Collection[str] | None = None,
    ) -> Twist2D:
        """`command`, slowed down where it would close on another robot too fast (the
        limiter must then brake at `decel_mps2`: see `cut`); `near`: see `keep_apart`.
        """
        kept = keep_apart(
            command,
            pose,
            peers,
            own_id=self.robot_id,
            contact_m=self.contact_m,
            decel_mps2=self.decel_mps2,
            latency_s=self.latency_s,
            near=near,
        )
        self.cut = kept is not command
        self.cuts += self.cut
        return kept


def near_radius_m(
    contact_m: float, *, v_max_mps: float, decel_mps2: float, latency_s: float, horizon_s: float
) -> float:
    """How far apart (m, centre to centre) two robots may be now and still need keeping
    apart within `horizon_s`: contact, both driving at each other at `v_max_mps` meanwhile,
    and both braking distances.
    """
    braking = braking_gap_m(v_max_mps, decel_mps2=decel_mps2, latency_s=latency_s)
    return contact_m + 2.0 * v_max_mps * horizon_s + 2.0 * braking


def near_sets(
    positions: Mapping[str, tuple[float, float]], *, radius_m: float
) -> dict[str, frozenset[str]]:
    """For every robot, the others within `radius_m` of it (all pairs at once)."""
    ids = list(positions)
    xy = np.array([positions[r] for r in ids], dtype=np.float64).reshape(-1, 2)
    d2 = (xy[:, None, 0] - xy[None, :, 0]) ** 2 + (xy[:, None, 1] - xy[None, :, 1]) ** 2
    close = d2 < radius_m * radius_m
    return {rid: frozenset(ids[j] for j in np.flatnonzero(close[i])) for i, rid in enumerate(ids)}
