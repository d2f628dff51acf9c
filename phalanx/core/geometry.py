"""Planar geometry in SI units: poses, twists, angle wrapping, frames, unicycle motion.

Conventions (docs/ARCHITECTURE.md): metres, radians, seconds; angles counter-clockwise; a body
frame has x along the robot's heading and y to its left.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from phalanx.core.frozen import quick_init

TWO_PI = 2.0 * math.pi
_SMALL_OMEGA_RADPS = 1e-9


def wrap_angle(angle_rad: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return (angle_rad + math.pi) % TWO_PI - math.pi


@quick_init
@dataclass(frozen=True, slots=True)
class Vec2:
    """A point or vector in a plane, metres."""

    x_m: float
    y_m: float

    def __add__(self, other: Vec2) -> Vec2:
        return Vec2(self.x_m + other.x_m, self.y_m + other.y_m)

    def __sub__(self, other: Vec2) -> Vec2:
        return Vec2(self.x_m - other.x_m, self.y_m - other.y_m)

    def norm(self) -> float:
        """Euclidean length, metres."""
        return math.hypot(self.x_m, self.y_m)

    def rotated(self, angle_rad: float) -> Vec2:
        """The vector rotated counter-clockwise by `angle_rad`."""
        c, s = math.cos(angle_rad), math.sin(angle_rad)
        return Vec2(c * self.x_m - s * self.y_m, s * self.x_m + c * self.y_m)


@quick_init
@dataclass(frozen=True, slots=True)
class Pose2D:
    """A robot pose in the world frame: position (m) and heading (rad)."""

    x_m: float
    y_m: float
    theta_rad: float

    @property
    def position(self) -> Vec2:
        """The pose's position."""
        return Vec2(self.x_m, self.y_m)

    def to_world(self, local: Vec2) -> Vec2:
        """Map a point given in this pose's body frame to the world frame."""
        return self.position + local.rotated(self.theta_rad)

    def to_body(self, point: Vec2) -> Vec2:
        """Map a world point into this pose's body frame."""
        return (point - self.position).rotated(-self.theta_rad)

    def compose(self, local: Pose2D) -> Pose2D:
        """`local` (a pose in this pose's frame) in the world frame: self * local."""
        p = self.to_world(local.position)
        return Pose2D(p.x_m, p.y_m, wrap_angle(self.theta_rad + local.theta_rad))

    def relative(self, other: Pose2D) -> Pose2D:
        """`other` (a world pose) in this pose's frame: the inverse of `compose`."""
        p = self.to_body(other.position)
        return Pose2D(p.x_m, p.y_m, wrap_angle(other.theta_rad - self.theta_rad))


@quick_init
@dataclass(frozen=True, slots=True)
class Twist2D:
    """A unicycle velocity: forward speed (m/s) and yaw rate (rad/s, counter-clockwise)."""

    v_mps: float
    omega_radps: float


ZERO_TWIST = Twist2D(0.0, 0.0)


def integrate_unicycle(pose: Pose2D, twist: Twist2D, dt_s: float) -> Pose2D:
    """Exact pose after moving with a constant twist for `dt_s` seconds (arc, not Euler)."""
    v, w, th = twist.v_mps, twist.omega_radps, pose.theta_rad
    if abs(w) < _SMALL_OMEGA_RADPS:
        # Second-order term keeps the formula smooth as omega -> 0.
        mid = th + 0.5 * w * dt_s
        return Pose2D(
            pose.x_m + v * dt_s * math.cos(mid),
            pose.y_m + v * dt_s * math.sin(mid),
            wrap_angle(th + w * dt_s),
        )
    th_new = th + w * dt_s
    radius_m = v / w
    return Pose2D(
        pose.x_m + radius_m * (math.sin(th_new) - math.sin(th)),
        pose.y_m - radius_m * (math.cos(th_new) - math.cos(th)),
        wrap_angle(th_new),
    )


def dead_reckon(pose: Pose2D, twist: Twist2D, age_s: float, max_age_s: float) -> Pose2D:
    """`pose`, measured `age_s` ago, carried forward along `twist` to now.

    A reading is carried forward at most `max_age_s` (a stale one is not extrapolated
    without bound) and never backwards (a stamp slightly ahead of the clock is now).
    """
    age_s = min(age_s, max_age_s)
    if age_s <= 0.0:
        return pose
    return integrate_unicycle(pose, twist, age_s)


def polar_to_slot(l_m: float, phi_rad: float) -> Vec2:
    """A slot at distance `l_m` and bearing `phi_rad` in a leader's body frame.

    phi is counter-clockwise from the leader's heading: pi = directly behind,
    3pi/4 = behind-left. The paper writes `X_L - l cos(phi + theta_L)`, the opposite
    sign; translate with `phi_ours = phi_paper + pi`.
    """
    return Vec2(l_m * math.cos(phi_rad), l_m * math.sin(phi_rad))


def slot_to_polar(slot: Vec2) -> tuple[float, float]:
    """(l in m, phi in rad within [0, 2 pi)) of a slot given in a leader's body frame."""
    return slot.norm(), math.atan2(slot.y_m, slot.x_m) % TWO_PI
