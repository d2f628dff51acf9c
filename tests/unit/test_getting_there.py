"""The rules that decide whether a navigating group tries again: STUCK only when the map
proves there is no way, and no robot takes the lead from behind another."""

from __future__ import annotations

import numpy as np
import pytest

from phalanx.agents.agent import Agent
from phalanx.agents.navigation.grid import OCCUPIED
from phalanx.core.geometry import Pose2D
from phalanx.core.scenarios import navigation_scenario
from phalanx.runtime.batch import BatchRunner


def _agent(shape: str, robot_id: str = "r1") -> Agent:
    scenario = navigation_scenario("field", shape, 3, seed=0)  # type: ignore[arg-type]
    return BatchRunner(scenario).agents[robot_id]


def test_past_its_retries_a_leader_goes_on_while_the_map_shows_a_way() -> None:
    agent = _agent("wedge")
    parts, pose = agent.parts, Pose2D(0.0, 0.0, 0.0)
    parts.progress.deadlocks = agent.scenario.deadlock.max_retries
    assert parts.planner.map is not None
    assert parts.retries_left(pose, deadlocked=True)  # nothing seen yet: a way
    grid = parts.planner.map
    row, col, _ = grid.index(np.array([0.0]), np.array([0.0]))
    r, c = int(row[0]), int(col[0])
    ring = np.zeros_like(grid.evidence, dtype=bool)
    ring[r - 4 : r + 5, c - 4 : c + 5] = True
    ring[r - 3 : r + 4, c - 3 : c + 4] = False
    grid.evidence[ring] = OCCUPIED  # walled in, two metres round
    assert not parts.retries_left(pose, deadlocked=True)


def test_within_its_retries_a_leader_always_tries_again() -> None:
    parts = _agent("wedge").parts
    parts.progress.deadlocks = 0
    assert parts.retries_left(Pose2D(0.0, 0.0, 0.0), deadlocked=True)


@pytest.mark.parametrize(
    ("shape", "robot_id", "behind_another"),
    [
        ("inline", "r1", False),
        ("inline", "r2", True),
        ("inline", "r3", True),
        ("wedge", "r2", False),
        ("collateral", "r3", False),
    ],
)
def test_only_a_robot_behind_another_in_the_shape_counts_one_ahead(
    shape: str, robot_id: str, behind_another: bool
) -> None:
    assert _agent(shape, robot_id).parts.senses.robot_ahead is behind_another
