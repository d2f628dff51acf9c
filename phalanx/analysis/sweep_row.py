"""The record of one run of a sweep, as a results file holds it (a JSON line each):
`phalanx sweep` writes it, and reads it back to resume and to draw its table; `phalanx
sweep-compare` pairs two files' records. A results file may have been cut short, edited,
or written by another version: a line is taken only if it is such a record, every field
within what a run writes (`SweepRow.of`); any other is skipped and counted.

NaN stands where a run measured nothing (no calm step, no route, no step to share).
"""

from __future__ import annotations

import math
from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError

from phalanx.core.config import MAX_ROBOTS
from phalanx.core.quantities import MAX_DURATION_S, Duration
from phalanx.wire.bounds import Count

# The largest formation error a run records (per cent, deg, m: a follower a world away).
MAX_ERROR = 1e9


def _share(value: float) -> float:
    if not (math.isnan(value) or 0.0 <= value <= 1.0):
        raise ValueError(f"{value} is not a share from 0 to 1")
    return value


def _time(value: float) -> float:
    if not (math.isnan(value) or 0.0 <= value <= MAX_DURATION_S):
        raise ValueError(f"{value} is not a time from 0 to {MAX_DURATION_S:g} s")
    return value


def _error(value: float) -> float:
    if not (math.isnan(value) or 0.0 <= value <= MAX_ERROR):
        raise ValueError(f"{value} is not a formation error from 0 to {MAX_ERROR:g}")
    return value


Share = Annotated[float, AfterValidator(_share)]  # 0..1, or NaN
Time = Annotated[float, AfterValidator(_time)]  # s, or NaN
Error = Annotated[float, AfterValidator(_error)]  # or NaN
Text = Annotated[str, Field(max_length=2000)]


class _Record(BaseModel):
    # (strict: a count is a whole number, not 5.0 or true; a share is a number, not "0.5")
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


class JobRecord(_Record):
    """Which run it was (`phalanx.analysis.sweep.Job`)."""

    course: Text
    shape: Text
    robots: Annotated[int, Field(ge=1, le=MAX_ROBOTS)]
    seed: Annotated[int, Field(ge=0, le=2**63 - 1)]
    controller: Text = "ours"
    overrides: tuple[tuple[Text, Any], ...] = ()


class ErrorStat(_Record):
    """One of the paper's errors over the followers' calm steps."""

    mean: Error
    max: Error


class CalmErrors(_Record):
    """The paper's errors outside avoidance episodes."""

    samples: Count
    linear_pct: ErrorStat
    angular_pct: ErrorStat
    orientation_deg: ErrorStat
    linear_m: ErrorStat
    angular_deg: ErrorStat


class SweepRow(_Record):
    """One run: which it was, its wall time, the route at cruise, and its navigation
    metrics (`phalanx.analysis.metrics.navigation_metrics`). The shape fields came
    later: a line from before them reads as in the shape all the time.
    """

    job: JobRecord
    key: Text
    wall_s: Duration
    route_s: Time
    goal_reached: bool
    time_to_goal_s: Duration | None
    collisions_obstacle: Count
    collisions_robot: Count
    deadlock_reverses: Count
    leadership_changes: Count
    stuck: bool
    stuck_reason: Text
    episode_share: Share
    reshaping_share: Share = 0.0
    calm: CalmErrors
    reshapes: Count = 0
    scenario_shape_share: Share = 1.0
    fits_share: Share = 1.0
    scenario_shape_when_fits: Share = 1.0

    @classmethod
    def read(cls, line: str) -> dict[str, Any]:
        """A results file's line (JSON, NaN allowed) as the row it holds; ValidationError
        if it holds none.
        """
        return cls.model_validate_json(line).model_dump()

    @classmethod
    def of(cls, line: str) -> dict[str, Any] | None:
        """`read`, or None for a line that holds no row."""
        try:
            return cls.read(line)
        except ValidationError:
            return None
