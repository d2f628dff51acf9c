"""What a robot reports, whatever drives it: odometry and the rest of its status. The
simulated world, every driver backend and the agent's observation use these types.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from phalanx.core.config import Scenario
from phalanx.core.geometry import Pose2D, Twist2D


@dataclass(frozen=True, slots=True)
class Odometry:
    """Dead-reckoned pose (odometry frame) and measured twist, at `stamp_s` (monotonic)."""

    pose: Pose2D
    twist: Twist2D
    stamp_s: float


@dataclass(frozen=True, slots=True)
class RobotStatus:
    """Everything a driver reads from a robot besides odometry."""

    sonar_ranges_m: tuple[float, ...] = ()
    bumpers: tuple[bool, ...] = ()
    battery_v: float | None = None
    motors_enabled: bool = False
    estopped: bool = False
    stalled: bool = False
    faults: tuple[str, ...] = field(default_factory=tuple)


def start_pose(scenario: Scenario, robot_id: str) -> Pose2D:
    """The robot's start pose in the world frame, from the scenario."""
    start = next(r.start for r in scenario.robots if r.id == robot_id)
    return Pose2D(start.x_m, start.y_m, math.radians(start.theta_deg))
