"""What a number in a file or a message may be: bounds set by what physics allows any
robot phalanx drives and any world it drives in, and the typed aliases the config models
declare their fields with (the wire's messages build theirs on the same bounds,
`phalanx.wire.bounds`).

A number outside them is a typo or an attack, never a value: it is refused where it is
read, with the field's name, before it can overflow an integer, make a run of no step,
or command a robot faster than any is rated.
"""

from __future__ import annotations

import math
from typing import Annotated, Final

from pydantic import Field

MAX_DURATION_S: Final = 86_400.0  # a day of fleet time
MAX_SPEED_MPS: Final = 10.0  # no differential-drive robot phalanx drives is rated faster
MAX_YAW_RATE_RADPS: Final = 20.0  # about 1150 deg/s
MAX_YAW_RATE_DEGPS: Final = math.degrees(MAX_YAW_RATE_RADPS)
MAX_ACCEL_MPS2: Final = 100.0  # about 10 g
MAX_YAW_ACCEL_DEGPS2: Final = 100_000.0
MAX_EXTENT_M: Final = 1e6  # a world a thousand kilometres across
MAX_RANGE_M: Final = 100.0  # sonar, cameras: any range sensor a robot carries
MAX_BODY_M: Final = 10.0  # a robot's size, and where on it a sensor sits
MAX_GAIN_PER_S: Final = 1000.0  # a control gain (1/s, or unitless per step)
MAX_VOLTAGE_V: Final = 1000.0
MAX_ANGLE_DEG: Final = 360.0  # a heading or bearing, either way round
# A robot on a driver stops when no command came for its watchdog's time: a safety stop,
# never long (1.2 m/s for 10 s is 12 m driven on the last command).
MAX_WATCHDOG_S: Final = 10.0

# Positions in the world or the formation's frame (m).
Coordinate = Annotated[float, Field(ge=-MAX_EXTENT_M, le=MAX_EXTENT_M)]
# Distances: along the way, between robots, to back off (m).
Length = Annotated[float, Field(ge=0.0, le=MAX_EXTENT_M)]
PositiveLength = Annotated[float, Field(gt=0.0, le=MAX_EXTENT_M)]
# What a robot senses at, and margins kept round its body (m).
SensorRange = Annotated[float, Field(ge=0.0, le=MAX_RANGE_M)]
PositiveRange = Annotated[float, Field(gt=0.0, le=MAX_RANGE_M)]
# A robot's own dimensions, and places on its body (m).
BodyLength = Annotated[float, Field(gt=0.0, le=MAX_BODY_M)]
BodyOffset = Annotated[float, Field(ge=-MAX_BODY_M, le=MAX_BODY_M)]
# Times within a run (s).
Duration = Annotated[float, Field(ge=0.0, le=MAX_DURATION_S)]
PositiveDuration = Annotated[float, Field(gt=0.0, le=MAX_DURATION_S)]
# Speeds (m/s): a rating or a limit, and a signed command.
PositiveSpeed = Annotated[float, Field(gt=0.0, le=MAX_SPEED_MPS)]
NonNegativeSpeed = Annotated[float, Field(ge=0.0, le=MAX_SPEED_MPS)]
SignedSpeed = Annotated[float, Field(ge=-MAX_SPEED_MPS, le=MAX_SPEED_MPS)]
# Yaw rates (deg/s), the same two ways.
PositiveYawRate = Annotated[float, Field(gt=0.0, le=MAX_YAW_RATE_DEGPS)]
SignedYawRate = Annotated[float, Field(ge=-MAX_YAW_RATE_DEGPS, le=MAX_YAW_RATE_DEGPS)]
PositiveAccel = Annotated[float, Field(gt=0.0, le=MAX_ACCEL_MPS2)]
PositiveYawAccel = Annotated[float, Field(gt=0.0, le=MAX_YAW_ACCEL_DEGPS2)]
# Headings and bearings (deg).
Angle = Annotated[float, Field(ge=-MAX_ANGLE_DEG, le=MAX_ANGLE_DEG)]
Gain = Annotated[float, Field(gt=0.0, le=MAX_GAIN_PER_S)]
Voltage = Annotated[float, Field(gt=0.0, le=MAX_VOLTAGE_V)]
Fraction = Annotated[float, Field(ge=0.0, le=1.0)]
