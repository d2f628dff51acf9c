"""Relative measurements of another robot as the pose filter uses them.

With range, bearing and relative heading (a fiducial marker gives all three) the
measurement, with the other robot's pose, fixes this robot's whole pose: it becomes a
pose fix with the measurement's and the other pose's covariance carried through (the fast
path, the same update as motion capture's). With range and bearing only (a laser), it is
an ordinary EKF update with the two rows.
"""

from __future__ import annotations

import math

from phalanx.agents.estimation.ekf import Belief, update, wrap
from phalanx.core.fixes import Cov6, RelativeFix
from phalanx.core.geometry import Pose2D


def as_pose_fix(
    rel: RelativeFix, other: Pose2D, carried: tuple[float, float, float]
) -> tuple[tuple[float, float, float], Cov6]:
    """The measuring robot's pose (x, y, theta) and its covariance, from a relative measurement
    with heading of a robot at `other`, whose pose is uncertain by `carried` (variances
    of x, y, theta).

    theta = theta_o - h; p = p_o - rho (cos phi, sin phi) with phi = theta + bearing.
    """
    assert rel.heading_rad is not None  # noqa: S101 - the caller checks
    theta = wrap(other.theta_rad - rel.heading_rad)
    phi = theta + rel.bearing_rad
    c, s, rho = math.cos(phi), math.sin(phi), rel.range_m
    z = (other.x_m - rho * c, other.y_m - rho * s, theta)
    vr, vx, vy = rel.std_range_m**2, carried[0], carried[1]
    vt = rel.std_heading_rad**2 + carried[2]  # the heading's, and the other's turned
    va = rel.std_bearing_rad**2 + vt  # every error that turns the line of sight
    r2 = rho * rho
    cov = (
        c * c * vr + r2 * s * s * va + vx,
        c * s * vr - r2 * s * c * va,
        rho * s * vt,
        s * s * vr + r2 * c * c * va + vy,
        -rho * c * vt,
        vt,
    )
    return z, cov


def update_range_bearing(
    b: Belief, rel: RelativeFix, other: Pose2D, carried: tuple[float, float, float], gate: float
) -> Belief | None:
    """The EKF update with range and bearing of a robot at `other` (variances `carried`)."""
    dx, dy = other.x_m - b.x, other.y_m - b.y
    r2 = dx * dx + dy * dy
    if r2 < 1e-6:
        return None
    rng = math.sqrt(r2)
    h = [[-dx / rng, -dy / rng, 0.0], [dy / r2, -dx / r2, -1.0]]
    nu = [rel.range_m - rng, wrap(rel.bearing_rad - (math.atan2(dy, dx) - b.th))]
    # the other robot's position error seen through the same rows (its Jacobian is -h)
    r = [
        [
            (rel.std_range_m**2 if i == 0 else rel.std_bearing_rad**2) * (i == j)
            + h[i][0] * h[j][0] * carried[0]
            + h[i][1] * h[j][1] * carried[1]
            for j in range(2)
        ]
        for i in range(2)
    ]
    return update(b, h, nu, r, gate)
