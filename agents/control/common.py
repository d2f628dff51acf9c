"""What every follower controller reads, and the exact rigid-body target they aim at.

Slot convention (DESIGN.md): the follower's slot is `s = (l cos phi, l sin phi)` in the
leader's body frame, phi counter-clockwise from the leader's heading.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

from phalanx.geometry import Pose2D, Twist2D, Vec2, dead_reckon, wrap_angle

# Below this slot speed (m/s) the heading offset beta fades to zero, so the target heading
# has no jump when the leader stops and reverses.
BETA_FADE_MPS = 0.01


@dataclass(frozen=True, slots=True)
class FollowerInput:
    """One control step's inputs for a follower (SI units, world frame)."""

    follower: Pose2D
    follower_twist: Twist2D
    leader: Pose2D
    leader_twist: Twist2D
    leader_age_s: float
    slot: Vec2
    direction: int
    dt_s: float


class FollowerController(Protocol):
    """A follower control law: inputs in, unsaturated twist out."""

    def command(self, inp: FollowerInput) -> Twist2D:
        """The twist the follower should drive now (before limits)."""
        ...

    def reset(self) -> None:
        """Forget any internal state."""
        ...


def predict_leader(leader: Pose2D, twist: Twist2D, age_s: float) -> Pose2D:
    """Dead-reckon the leader's pose `age_s` seconds ahead along its twist (exact arc)."""
    return dead_reckon(leader, twist, age_s, math.inf)


def slot_velocity(twist: Twist2D, slot: Vec2) -> Vec2:
    """Velocity of the slot point, leader body frame: `(v - w s_y, w s_x)` (rigid body)."""
    return Vec2(twist.v_mps - twist.omega_radps * slot.y_m, twist.omega_radps * slot.x_m)


def heading_offset(u: Vec2) -> float:
    """beta: the follower's heading relative to the leader's, for slot velocity `u`.

    A nonholonomic robot can only move along its axis, so it must point along the slot
    velocity: `beta = atan(u_y / u_x)`, within +-90 deg so the robot keeps facing the way
    the formation faces whether it drives forwards (u_x > 0) or backwards (u_x < 0). The
    factor `1 - exp(-(u_x / BETA_FADE_MPS)^2)` fades beta to zero as u_x crosses zero
    (the leader stopping to reverse), so the target heading never jumps; at the paper's
    speeds it differs from 1 by less than 1e-12.
    """
    if u.x_m == 0.0:
        return 0.0
    fade = 1.0 - math.exp(-((u.x_m / BETA_FADE_MPS) ** 2))
    return math.atan(u.y_m / u.x_m) * fade


def rigid_body_target(leader: Pose2D, twist: Twist2D, slot: Vec2) -> tuple[Pose2D, Twist2D]:
    """The pose and feed-forward twist of a follower moving rigidly with the leader.

    Position: the slot point. Heading: `theta_L + beta` (DESIGN.md), so a nonholonomic
    robot can move with the slot point. Twist: the signed slot speed along that heading
    and the leader's yaw rate (beta is constant for a constant leader twist).
    """
    position = leader.to_world(slot)
    u = slot_velocity(twist, slot)
    beta = heading_offset(u)
    speed = u.x_m * math.cos(beta) + u.y_m * math.sin(beta)
    heading = wrap_angle(leader.theta_rad + beta)
    return Pose2D(position.x_m, position.y_m, heading), Twist2D(speed, twist.omega_radps)
