"""The model of a robot parameter file (`configs/robots/*.toml`): a differential-drive
robot's geometry, speed and acceleration limits, braking and sonar ring, in SI units.
`phalanx.core.config_files.load_robot` reads one by name.
"""

from __future__ import annotations

import math
from typing import Self

from pydantic import Field, model_validator

from phalanx.core.config import Model, NonNegativeFloat, PositiveFloat


class SonarUnit(Model):
    """One sonar transducer: position (m) and heading (deg) in the robot's body frame."""

    x_m: float
    y_m: float
    heading_deg: float


class SonarParams(Model):
    """The sonar ring."""

    max_range_m: PositiveFloat = 5.0
    min_range_m: NonNegativeFloat = 0.1
    beam_width_deg: PositiveFloat = 15.0
    rays_per_beam: int = Field(default=3, ge=1, le=15)
    units: tuple[SonarUnit, ...] = Field(max_length=64)


class RobotParams(Model):
    """Kinematic and physical parameters of a differential-drive robot (SI units)."""

    name: str
    track_width_m: PositiveFloat
    wheel_radius_m: PositiveFloat
    radius_m: PositiveFloat
    v_max_mps: PositiveFloat
    omega_max_degps: PositiveFloat
    wheel_v_max_mps: PositiveFloat
    accel_mps2: PositiveFloat
    decel_mps2: PositiveFloat
    rot_accel_degps2: PositiveFloat
    sonar: SonarParams
    # Below this the agent stops the robot (LOW_BATTERY) until it is charged; none: no check.
    battery_low_v: PositiveFloat | None = None
    # How hard the robot may brake when it must stop now (HOLD: its leader is gone), rather
    # than the comfortable `decel_mps2`/`rot_accel_degps2`; none: the comfortable ones.
    emergency_decel_mps2: PositiveFloat | None = None
    emergency_rot_decel_degps2: PositiveFloat | None = None

    @model_validator(mode="after")
    def _emergency_is_harder(self) -> Self:
        if self.emergency_decel_mps2 is not None and self.emergency_decel_mps2 < self.decel_mps2:
            raise ValueError("emergency_decel_mps2 must be at least decel_mps2")
        rot = self.emergency_rot_decel_degps2
        if rot is not None and rot < self.rot_accel_degps2:
            raise ValueError("emergency_rot_decel_degps2 must be at least rot_accel_degps2")
        return self

    @property
    def omega_max_radps(self) -> float:
        """Yaw-rate limit, rad/s."""
        return math.radians(self.omega_max_degps)

    @property
    def rot_accel_radps2(self) -> float:
        """Yaw acceleration limit, rad/s^2."""
        return math.radians(self.rot_accel_degps2)

    @property
    def emergency_decel(self) -> tuple[float, float]:
        """The emergency braking limits: (m/s^2, rad/s^2)."""
        decel = self.emergency_decel_mps2 or self.decel_mps2
        rot = self.emergency_rot_decel_degps2 or self.rot_accel_degps2
        return decel, math.radians(rot)
