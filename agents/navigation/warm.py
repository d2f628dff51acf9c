"""Navigation's compiled kernels (`phalanx.core.compiled`) made ready ahead of a loop.

A process loads a kernel from numba's cache, or compiles it in a fresh environment, on
its first call: about half a second for the four, about 3 s when they compile. A
real-time loop must not wait for that at its first obstacle, so it calls `warm_kernels`
before it starts: each kernel once, on a small case of the same kinds of arrays the
navigation gives it.
"""

from __future__ import annotations

import numpy as np

from phalanx.agents.navigation.clearance import HEADINGS_RAD, corridor_clearance
from phalanx.agents.navigation.grid import OccupancyMap
from phalanx.agents.perception import SonarGeometry
from phalanx.core.geometry import Pose2D, Vec2


def warm_kernels(sonar: SonarGeometry) -> None:
    """Call each of navigation's kernels once (numpy's code runs instead where numba is
    not installed or not asked for): the clearance pass, turned and sliding; the map's
    update, with echoes near enough to mark; the route's wavefront; the arcs' test of
    which echoes are the fleet's robots.
    """
    points = (np.array([1.0]), np.array([0.0]))
    slots = (Vec2(0.0, 0.0), Vec2(-0.5, 0.5))
    for turning in (True, False):
        corridor_clearance(
            points, HEADINGS_RAD[:2], half_width_m=0.3, origins=slots, turning=turning
        )
    grid = OccupancyMap(Vec2(0.0, 0.0), half_size_m=3.0)
    units = sonar.unit_x_m.size
    grid.update(Pose2D(0.0, 0.0, 0.0), sonar, np.full(units, 1.0))
    grid.route_length_m(Vec2(-1.0, -1.0), Vec2(1.0, 1.0), footprint_m=0.0)
    cx, cy = np.zeros((1, 1)), np.ones((1, 1))
    met = np.zeros((1, units), dtype=bool)
    owner = np.zeros(1, dtype=np.intp)
    sonar.arcs_met(np.ones((1, units)), owner, (cx, cy), 0.3, sonar.nearest_dirs(cx, cy), met)
