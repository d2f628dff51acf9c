"""What a wire field may hold: the typed aliases every message field is one of, and
`FleetBounds`, what a receiver knows of its fleet to hold a message against.

Every field is bounded by what the protocol carries (unsigned 32-bit counters, int8
directions) and what physics allows any robot phalanx drives (speeds, extents, ranges). A
receiver that knows its fleet (`FleetBounds`, pydantic's validation context) checks more:
ids of its fleet only, speeds within the robot's rating, stamps and ticks within the run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Final

from pydantic import AfterValidator, Field, ValidationInfo

from phalanx.core.config import MAX_CONTROL_RATE_HZ, Scenario
from phalanx.core.peers import EPOCH_MAX, SEQ_MAX
from phalanx.core.quantities import (
    MAX_DURATION_S,
    MAX_RANGE_M,
    MAX_SPEED_MPS,
    MAX_YAW_RATE_RADPS,
)
from phalanx.core.robot_params import RobotParams
from phalanx.core.shapes import SHAPE_NAMES
from phalanx.core.states import State

# A new field takes the type of its kind and is checked the same way.

UINT32_MAX: Final = 2**32 - 1
# Fleet time runs from 0 at the run's start (sim time, or the shared epoch in real time).
MAX_STAMP_S: Final = MAX_DURATION_S + 3600.0
MAX_TEXT: Final = 500
MAX_SONARS: Final = 64
MAX_BUMPERS: Final = 32
# A receiver's rating check leaves this much room: measured speeds carry odometry noise.
RATING_MARGIN: Final = 1.5
ID_PATTERN: Final = r"^[A-Za-z0-9_-]{1,32}$"
_STATE_NAMES: Final = frozenset(str(s) for s in State)


@dataclass(frozen=True)
class FleetBounds:
    """What a receiver knows of its fleet, to hold a message against: its robots, their
    rating (m/s, rad/s), the run's length (s) and control period (s) and its ticks. Given
    to the decoder as pydantic's validation context; a message that fails is dropped and
    counted like any malformed one.
    """

    robot_ids: frozenset[str]
    v_max_mps: float
    omega_max_radps: float
    t_max_s: float
    dt_s: float
    ticks: int
    # Transducers in each robot's sonar ring (0: not known, not checked). The fleet's
    # map reads every scan with its own robot's ring, so a scan of another length is
    # no scan of this fleet.
    sonars: int = 0

    @classmethod
    def of(cls, scenario: Scenario, robot: RobotParams) -> FleetBounds:
        """The bounds of a run of `scenario` with robots of `robot`'s type."""
        ticks = round(scenario.duration_s * scenario.control_rate_hz)
        return cls(
            robot_ids=frozenset(r.id for r in scenario.robots),
            v_max_mps=robot.v_max_mps * RATING_MARGIN,
            omega_max_radps=robot.omega_max_radps * RATING_MARGIN,
            t_max_s=ticks * scenario.dt_s + 1.0,
            dt_s=scenario.dt_s,
            ticks=ticks,
            sonars=len(robot.sonar.units),
        )


def fleet_bounds(info: ValidationInfo) -> FleetBounds | None:
    """The fleet's bounds a message is validated against, if the decoder was given them."""
    context = info.context
    return context if isinstance(context, FleetBounds) else None


def _fleet_member(value: str, info: ValidationInfo) -> str:
    bounds = fleet_bounds(info)
    if bounds is not None and value and value not in bounds.robot_ids:
        raise ValueError(f"{value!r} is not a robot of this fleet")
    return value


def _within_rating_v(value: float, info: ValidationInfo) -> float:
    bounds = fleet_bounds(info)
    if bounds is not None and abs(value) > bounds.v_max_mps:
        raise ValueError(f"{value} m/s is beyond the robots' rating")
    return value


def _within_rating_w(value: float, info: ValidationInfo) -> float:
    bounds = fleet_bounds(info)
    if bounds is not None and abs(value) > bounds.omega_max_radps:
        raise ValueError(f"{value} rad/s is beyond the robots' rating")
    return value


def _within_run(value: float, info: ValidationInfo) -> float:
    bounds = fleet_bounds(info)
    if bounds is not None and value > bounds.t_max_s:
        raise ValueError(f"fleet time {value} s is past the run's end ({bounds.t_max_s} s)")
    return value


def _within_ticks(value: int, info: ValidationInfo) -> int:
    bounds = fleet_bounds(info)
    if bounds is not None and value > bounds.ticks:
        raise ValueError(f"tick {value} is past the run's last ({bounds.ticks})")
    return value


def _state_name(value: str) -> str:
    if value not in _STATE_NAMES:
        raise ValueError(f"{value[:40]!r} is not a behaviour state")
    return value


RobotId = Annotated[str, Field(pattern=ID_PATTERN), AfterValidator(_fleet_member)]
MaybeRobotId = Annotated[
    str, Field(pattern=r"^([A-Za-z0-9_-]{1,32})?$"), AfterValidator(_fleet_member)
]  # "" for nobody
Stamp = Annotated[float, Field(ge=0.0, le=MAX_STAMP_S), AfterValidator(_within_run)]
Tick = Annotated[int, Field(ge=0, le=UINT32_MAX), AfterValidator(_within_ticks)]
Period = Annotated[float, Field(ge=1.0 / MAX_CONTROL_RATE_HZ - 1e-12, le=10.0)]
Seconds = Annotated[float, Field(ge=0.0, le=MAX_STAMP_S)]  # a duration within a run
Count = Annotated[int, Field(ge=0, le=UINT32_MAX)]
Seq = Annotated[int, Field(ge=0, le=SEQ_MAX)]
Epoch = Annotated[int, Field(ge=0, le=EPOCH_MAX)]
Heading = Annotated[float, Field(ge=-2.0 * math.pi, le=2.0 * math.pi)]
Speed = Annotated[
    float, Field(ge=-MAX_SPEED_MPS, le=MAX_SPEED_MPS), AfterValidator(_within_rating_v)
]
YawRate = Annotated[
    float,
    Field(ge=-MAX_YAW_RATE_RADPS, le=MAX_YAW_RATE_RADPS),
    AfterValidator(_within_rating_w),
]
Range = Annotated[float, Field(ge=0.0, le=MAX_RANGE_M)]
StateName = Annotated[str, Field(max_length=32), AfterValidator(_state_name)]
Text = Annotated[str, Field(max_length=MAX_TEXT)]
Micros = Annotated[float, Field(ge=0.0, le=1e9)]
UnixStamp = Annotated[float, Field(ge=0.0, le=float(UINT32_MAX))]  # s since 1970, to 2106
# The shapes a group may be in (`phalanx.core.shapes`): an index beyond them is refused.
ShapeIndex = Annotated[int, Field(ge=0, le=len(SHAPE_NAMES) - 1)]
Morph = Annotated[float, Field(ge=0.0, le=1.0)]  # how far a slide between shapes has come
