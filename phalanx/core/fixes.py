"""What a robot's positioning sensors report, as plain values: absolute pose fixes (motion
capture, an overhead camera, UWB) and relative measurements of another robot (a camera
reading the fiducial marker on it, a laser). Each carries the time it was taken, on the
fleet clock, so a late one is applied at its own time, never as if it were new.

A pose covariance travels as the upper triangle of its symmetric 3x3 matrix in the order
`(xx, xy, xt, yy, yt, tt)` (m^2, m^2, m rad, m^2, m rad, rad^2), the order `PeerState.cov`
and the wire use too.
"""

from __future__ import annotations

from dataclasses import dataclass

from phalanx.core.geometry import Pose2D

# (xx, xy, xt, yy, yt, tt): the upper triangle of a 3x3 pose covariance.
Cov6 = tuple[float, float, float, float, float, float]


@dataclass(frozen=True, slots=True)
class PoseFix:
    """An absolute pose in the world frame (m, rad) taken at `stamp_s` (fleet clock), with
    its standard deviations: `std_m` on each of x and y, `std_rad` on the heading.
    """

    stamp_s: float
    x_m: float
    y_m: float
    theta_rad: float
    std_m: float
    std_rad: float

    @property
    def pose(self) -> Pose2D:
        """The fixed pose."""
        return Pose2D(self.x_m, self.y_m, self.theta_rad)


@dataclass(frozen=True, slots=True)
class RelativeFix:
    """Robot `target_id` seen from this robot at `stamp_s` (fleet clock): `range_m` from
    this robot's centre to the target's, `bearing_rad` counter-clockwise from this robot's
    heading, and (when the sensor gives it, e.g. a fiducial marker) the target's heading
    relative to this robot's, `heading_rad`; with their standard deviations.

    The paper's (l, phi) of a follower seen from its leader are the same quantities the
    other way round: a follower that measures them needs no shared frame.
    """

    stamp_s: float
    target_id: str
    range_m: float
    bearing_rad: float
    std_range_m: float
    std_bearing_rad: float
    heading_rad: float | None = None
    std_heading_rad: float = 0.0


def cov_of_stds(std_x_m: float, std_y_m: float, std_theta_rad: float) -> Cov6:
    """A diagonal pose covariance from standard deviations."""
    return (std_x_m**2, 0.0, 0.0, std_y_m**2, 0.0, std_theta_rad**2)
