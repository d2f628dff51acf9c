"""The leader's route: a coarse obstacle map from the sonar ring and, over it, where to
head for next on the way to a goal (re-planned every `REPLAN_S`).
"""

from __future__ import annotations

import math

from phalanx.agents.mapping import OccupancyMap
from phalanx.agents.perception import BoolArray, FloatArray, SonarGeometry
from phalanx.core.geometry import Pose2D, Vec2

# Route re-planning period (s) and how far along the route to head for (m).
REPLAN_S = 1.0
ROUTE_AHEAD_M = 2.0


class RoutePlanner:
    """The map a robot builds from its own sonar and the route it plans over it. Without
    a map (none built yet, or a scripted leader) the route is straight for the goal.
    """

    def __init__(self, *, keep_off_m: float) -> None:
        self.keep_off_m = keep_off_m
        self.map: OccupancyMap | None = None
        self.carrot: Vec2 | None = None  # where the route leads next (world frame)
        self._planned_s = -math.inf

    def see(self, pose: Pose2D, sonar: SonarGeometry, ranges: FloatArray, echo: BoolArray) -> None:
        """Add a reading taken at `pose` (the map starts where the first one was taken)."""
        if self.map is None:
            self.map = OccupancyMap(pose.position)
        self.map.update(pose, sonar, ranges, echo)

    def towards(self, pose: Pose2D, goal: Vec2, t_s: float) -> Vec2:
        """Where to head for next: along the cheapest route round everything the sonar
        has shown so far (re-planned every `REPLAN_S`), which keeps the shape's half-width
        off obstacles where there is room and squeezes by where there is not (followers
        go round what the shape does not clear); straight for the goal without a map.
        """
        if self.map is None:
            return goal
        if t_s - self._planned_s >= REPLAN_S or self.carrot is None:
            self._planned_s = t_s
            self.carrot = self.map.route(
                pose.position, goal, keep_off_m=self.keep_off_m, ahead_m=ROUTE_AHEAD_M
            )
        return self.carrot or goal

    def forget_carrot(self) -> None:
        """Plan afresh next time (the robot stopped following the route)."""
        self.carrot = None
