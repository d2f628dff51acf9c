"""The model of a robot parameter file (`configs/robots/*.toml`): a differential-drive
robot's geometry, speed and acceleration limits, braking and sonar ring, in SI units.
`phalanx.core.config_files.load_robot` reads one by name.
"""

from __future__ import annotations

import math
from typing import Annotated, Self

from pydantic import Field, model_validator

from phalanx.core.config import Model
from phalanx.core.quantities import (
    Angle,
    BodyLength,
    BodyOffset,
    PositiveAccel,
    PositiveRange,
    PositiveSpeed,
    PositiveYawAccel,
    PositiveYawRate,
    SensorRange,
    Voltage,
)


class SonarUnit(Model):
    """One sonar transducer: position (m) and heading (deg) in the robot's body frame."""

    x_m: BodyOffset
    y_m: BodyOffset
    heading_deg: Angle


class SonarParams(Model):
    """The sonar ring."""

    max_range_m: PositiveRange = 5.0
    min_range_m: SensorRange = 0.1
    beam_width_deg: Annotated[float, Field(gt=0.0, le=180.0)] = 15.0
    rays_per_beam: int = Field(default=3, ge=1, le=15)
    units: tuple[SonarUnit, ...] = Field(max_length=64)

    @model_validator(mode="after")
    def _ranges(self) -> Self:
        if self.min_range_m >= self.max_range_m:
            raise ValueError("min_range_m must be below max_range_m")
        return self


class RobotParams(Model):
    """Kinematic and physical parameters of a differential-drive robot (SI units)."""

    name: str
    track_width_m: BodyLength
    wheel_radius_m: BodyLength
    radius_m: BodyLength
    v_max_mps: PositiveSpeed
    omega_max_degps: PositiveYawRate
    wheel_v_max_mps: PositiveSpeed
    accel_mps2: PositiveAccel
    decel_mps2: PositiveAccel
    rot_accel_degps2: PositiveYawAccel
    sonar: SonarParams
    # Below this the agent stops the robot (LOW_BATTERY) until it is charged; none: no check.
    battery_low_v: Voltage | None = None
    # How hard the robot may brake when it must stop now (HOLD: its leader is gone), rather
    # than the comfortable `decel_mps2`/`rot_accel_degps2`; none: the comfortable ones.
    emergency_decel_mps2: PositiveAccel | None = None
    emergency_rot_decel_degps2: PositiveYawAccel | None = None

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
