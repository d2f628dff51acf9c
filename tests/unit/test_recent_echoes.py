"""A navigator's memory of recent echoes (agents/navigation/steering.py: RecentEchoes)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from phalanx.agents.navigation import HEADINGS_RAD, RecentEchoes, corridor_clearance
from phalanx.agents.perception import FloatArray
from phalanx.core.geometry import Pose2D


def pts(*xy: tuple[float, float]) -> tuple[FloatArray, FloatArray]:
    return np.array([p[0] for p in xy], dtype=float), np.array([p[1] for p in xy], dtype=float)


def test_an_echo_stays_where_it_was_in_the_world_as_the_robot_moves_on() -> None:
    recent = RecentEchoes(1.0)
    recent.with_recent(Pose2D(0.0, 0.0, 0.0), pts((2.0, 0.0)), 0.0)
    # 0.5 s later, 1 m on and facing +y: nothing heard now, the obstacle still there
    x, y = recent.with_recent(Pose2D(1.0, 0.0, math.pi / 2), pts(), 0.5)
    assert x.tolist() == pytest.approx([0.0], abs=1e-12)
    assert y.tolist() == pytest.approx([-1.0])


def test_echoes_older_than_the_memory_are_forgotten() -> None:
    recent = RecentEchoes(1.0)
    recent.with_recent(Pose2D(0.0, 0.0, 0.0), pts((2.0, 0.0)), 0.0)
    x, _ = recent.with_recent(Pose2D(0.0, 0.0, 0.0), pts((3.0, 0.0)), 1.0)
    assert sorted(x.tolist()) == [2.0, 3.0]  # 1 s old: still remembered
    x, _ = recent.with_recent(Pose2D(0.0, 0.0, 0.0), pts(), 1.1)
    assert sorted(x.tolist()) == [3.0]
    x, _ = recent.with_recent(Pose2D(0.0, 0.0, 0.0), pts(), 60.0)  # led again a minute on
    assert x.size == 0


def test_an_obstacle_lost_between_two_beams_still_closes_the_way_to_it() -> None:
    recent = RecentEchoes(1.0)
    pose = Pose2D(0.0, 0.0, 0.0)
    ahead = int(np.argmin(np.abs(HEADINGS_RAD)))
    seen = recent.with_recent(pose, pts((1.5, 0.0)), 0.0)
    lost = recent.with_recent(pose, pts(), 0.1)  # this step's ring misses it
    free_seen = corridor_clearance(seen, HEADINGS_RAD, half_width_m=0.3)[ahead]
    free_lost = corridor_clearance(lost, HEADINGS_RAD, half_width_m=0.3)[ahead]
    assert free_lost == free_seen < 1.5
