"""The exact rigid-body motion of a formation slot: where a follower should be, which
way it should face and how fast it should go when the shape moves as one body with its
leader; and the paper's errors of a follower against a leader's published state.

Slot convention: a follower's slot is `s = (l cos phi, l sin phi)` in its leader's body
frame, phi counter-clockwise from the leader's heading (pi = directly behind).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

from phalanx.core.formation import Formation
from phalanx.core.geometry import Pose2D, Twist2D, Vec2, dead_reckon, wrap_angle


class LeaderState(Protocol):
    """What a follower knows of the robot it tracks: its pose and twist at `stamp_s`."""

    @property
    def robot_id(self) -> str: ...  # noqa: D102
    @property
    def stamp_s(self) -> float: ...  # noqa: D102
    @property
    def pose(self) -> Pose2D: ...  # noqa: D102
    @property
    def twist(self) -> Twist2D: ...  # noqa: D102


# Below this slot speed (m/s) the heading offset beta fades to zero, so the target heading
# has no jump when the leader stops and reverses.
BETA_FADE_MPS = 0.01


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
    return _beta(u.x_m, u.y_m)


def _beta(u_x: float, u_y: float) -> float:
    if u_x == 0.0:
        return 0.0
    fade = 1.0 - math.exp(-((u_x / BETA_FADE_MPS) ** 2))
    return math.atan(u_y / u_x) * fade


def rigid_body_target(leader: Pose2D, twist: Twist2D, slot: Vec2) -> tuple[Pose2D, Twist2D]:
    """The pose and feed-forward twist of a follower moving rigidly with the leader.

    Position: the slot point. Heading: `theta_L + beta` (see `heading_offset`), so a nonholonomic
    robot can move with the slot point. Twist: the signed slot speed along that heading
    and the leader's yaw rate (beta is constant for a constant leader twist).
    """
    # `leader.to_world(slot)` and `slot_velocity(twist, slot)` in plain floats (a step
    # of every follower runs this), operation for operation
    c, s = math.cos(leader.theta_rad), math.sin(leader.theta_rad)
    x_m = leader.x_m + (c * slot.x_m - s * slot.y_m)
    y_m = leader.y_m + (s * slot.x_m + c * slot.y_m)
    u_x, u_y = twist.v_mps - twist.omega_radps * slot.y_m, twist.omega_radps * slot.x_m
    beta = _beta(u_x, u_y)
    speed = u_x * math.cos(beta) + u_y * math.sin(beta)
    heading = wrap_angle(leader.theta_rad + beta)
    return Pose2D(x_m, y_m, heading), Twist2D(speed, twist.omega_radps)


@dataclass(frozen=True)
class LiveErrors:
    """One follower's errors at one step, against the leader state it used."""

    slot_target: Pose2D
    linear_pct: float
    angular_pct: float
    orientation_deg: float


def live_errors(
    formation: Formation, follower: str, pose: Pose2D, leader: LeaderState, *, t_s: float
) -> LiveErrors:
    """The paper's errors of `follower` at `pose` and fleet time `t_s` against `leader`'s
    published state, dead-reckoned over its age as the controller does (what a robot can
    know on its own, for live telemetry; `error_series` uses ground truth).
    """
    l_d, phi_d = formation.polar_of(follower, leader.robot_id)
    leader_pose = predict_leader(leader.pose, leader.twist, t_s - leader.stamp_s)
    local = leader_pose.to_body(pose.position)
    l_m = local.norm()
    phi = math.atan2(local.y_m, local.x_m) % (2 * math.pi)
    dphi = abs((phi - phi_d + math.pi) % (2 * math.pi) - math.pi)
    slot = formation.slot_of(follower, leader.robot_id)
    target, _ = rigid_body_target(leader_pose, leader.twist, slot)
    return LiveErrors(
        slot_target=target,
        linear_pct=100.0 * abs(l_m - l_d) / l_d,
        angular_pct=100.0 * dphi / phi_d,
        orientation_deg=math.degrees(abs(wrap_angle(pose.theta_rad - target.theta_rad))),
    )
