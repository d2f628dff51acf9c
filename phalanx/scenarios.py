"""Scenarios built in code: large grid formations for scaling benchmarks and tests."""

from __future__ import annotations

import math

from phalanx.config import (
    FormationConfig,
    RobotEntry,
    Scenario,
    SlotConfig,
    StartPose,
    validate_data,
)


def grid_formation(n: int, *, spacing_m: float = 2.0) -> FormationConfig:
    """`n` robots on a square grid behind the root, each following its neighbour.

    Row 0 is a chain to the right of the root; every other row hangs off the robot in
    front of it, so leader-state traffic stays O(followers of each robot).
    """
    cols = max(1, math.ceil(math.sqrt(n)))
    slots = []
    for i in range(n):
        row, col = divmod(i, cols)
        follows = None if i == 0 else (f"g{i - 1}" if row == 0 else f"g{i - cols}")
        slots.append(
            SlotConfig(robot=f"g{i}", follows=follows, x_m=-row * spacing_m, y_m=-col * spacing_m)
        )
    return FormationConfig(slots=tuple(slots))


def grid_scenario(base: Scenario, n: int, *, duration_s: float | None = None) -> Scenario:
    """`base` (its leader script, events, controller) with an `n`-robot grid formation."""
    formation = grid_formation(n)
    robots = tuple(
        RobotEntry(id=s.robot, start=StartPose(x_m=s.x_m or 0.0, y_m=s.y_m or 0.0))
        for s in formation.slots
    )
    data = base.model_dump()
    data.update(
        name=f"{base.name}-grid{n}",
        formation=formation.model_dump(),
        robots=[r.model_dump() for r in robots],
        duration_s=duration_s or base.duration_s,
    )
    return validate_data(Scenario, data, source=f"grid scenario of {n} robots")
