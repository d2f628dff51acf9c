"""Velocity and acceleration bounds of a differential-drive robot, and the one rule that
derives a run's bounds from the robot's rating and a scenario's run limits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from phalanx.core.config import LimitsOverride
from phalanx.core.robot_params import RobotParams


@dataclass(frozen=True, slots=True)
class KinematicLimits:
    """Velocity and acceleration bounds of a differential-drive robot (SI)."""

    v_max_mps: float
    omega_max_radps: float
    wheel_v_max_mps: float
    track_width_m: float
    accel_mps2: float
    decel_mps2: float
    rot_accel_radps2: float
    # Braking to a stop that cannot wait (HOLD), m/s^2 and rad/s^2: the robot file's
    # emergency limits (its comfortable ones when it gives none).
    emergency_decel_mps2: float = 0.0
    emergency_rot_decel_radps2: float = 0.0

    @classmethod
    def from_params(
        cls, robot: RobotParams, override: LimitsOverride | None = None
    ) -> KinematicLimits:
        """The robot's limits, tightened by a scenario's run bounds where given."""
        v_max, w_max = robot.v_max_mps, robot.omega_max_radps
        if override is not None and override.v_max_mps is not None:
            v_max = min(v_max, override.v_max_mps)
        if override is not None and override.omega_max_degps is not None:
            w_max = min(w_max, math.radians(override.omega_max_degps))
        return cls(
            v_max_mps=v_max,
            omega_max_radps=w_max,
            wheel_v_max_mps=robot.wheel_v_max_mps,
            track_width_m=robot.track_width_m,
            accel_mps2=robot.accel_mps2,
            decel_mps2=robot.decel_mps2,
            rot_accel_radps2=robot.rot_accel_radps2,
            emergency_decel_mps2=robot.emergency_decel[0],
            emergency_rot_decel_radps2=robot.emergency_decel[1],
        )


@dataclass(frozen=True)
class SafetyLimits:
    """The outer safety layer's bounds (`phalanx.drivers.safety.SafeDriver`): speeds
    (m/s, rad/s) and the command watchdog (s).
    """

    v_max_mps: float
    omega_max_radps: float
    watchdog_s: float = 0.5


def run_limits(robot: RobotParams, override: LimitsOverride | None = None) -> KinematicLimits:
    """A run's bounds: the robot's rating, tightened by the scenario's run limits where
    they are tighter (a scenario can never loosen the robot's rating). The limiter after
    every controller and the safety layer around every driver both use these.
    """
    return KinematicLimits.from_params(robot, override)


def safety_limits(
    robot: RobotParams, override: LimitsOverride | None = None, *, watchdog_s: float = 0.5
) -> SafetyLimits:
    """The safety layer's bounds for a run: the same speeds as `run_limits`."""
    limits = run_limits(robot, override)
    return SafetyLimits(limits.v_max_mps, limits.omega_max_radps, watchdog_s)
