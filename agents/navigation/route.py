"""The route: where to head for next on the way to a goal, over the map the fleet builds
(re-planned every `REPLAN_S`, so it follows the map as it grows).

With a fleet map (`phalanx.agents.navigation.fleet_map`, every navigating scenario) a robot's own
reading goes into its next `Scan`, shared with the fleet and added to the map with the
others' at the start of the next step; without one (a robot given none), the robot's
own map takes its readings at once, as it always did.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from phalanx.agents.navigation.fleet_map import FleetMap, scan_of
from phalanx.agents.navigation.grid import OccupancyMap, Planned
from phalanx.agents.perception import BoolArray, FloatArray, SonarGeometry
from phalanx.core.geometry import Pose2D, Vec2
from phalanx.core.peers import Scan

# Route re-planning period (s) and how far along the route to head for (m).
REPLAN_S = 1.0
ROUTE_AHEAD_M = 2.0


class RoutePlanner:
    """The map a robot reads (its own, or the fleet's) and the route it plans over it.
    Without a map (none built yet, or a scripted leader) the route is straight for the goal.
    """

    def __init__(self, *, keep_off_m: float, robot_id: str = "") -> None:
        self.keep_off_m = keep_off_m
        self.robot_id = robot_id
        self.fleet: FleetMap | None = None
        self._own: OccupancyMap | None = None
        self.carrot: Vec2 | None = None  # where the route leads next (world frame)
        self.points: tuple[Vec2, ...] = ()  # the route last planned (world frame)
        self.scan: Scan | None = None  # this robot's last reading, for the fleet
        self._planned_s = -math.inf

    @property
    def map(self) -> OccupancyMap | None:
        """The map the route is planned over."""
        return self.fleet.map if self.fleet is not None else self._own

    def share(self, fleet: FleetMap) -> None:
        """Plan over `fleet`, and feed it (a batch runner gives all its robots one)."""
        self.fleet = fleet

    def add(self, scans: Iterable[Scan]) -> None:
        """The fleet's scans heard since the last step, and this robot's own last one."""
        if self.fleet is None:
            return
        own = (self.scan,) if self.scan is not None else ()
        self.fleet.add((*scans, *own))

    def see(
        self,
        pose: Pose2D,
        sonar: SonarGeometry,
        ranges: FloatArray,
        echo: BoolArray,
        t_s: float = 0.0,
    ) -> None:
        """A reading taken at `pose` at `t_s`: the scan to share (with a fleet map), or
        into this robot's own map (which starts where the first one was taken).
        """
        if self.fleet is not None:
            self.scan = scan_of(self.robot_id, t_s, pose, ranges, echo)
            return
        if self._own is None:
            self._own = OccupancyMap(pose.position)
        self._own.update(pose, sonar, ranges, echo)

    def towards(self, pose: Pose2D, goal: Vec2, t_s: float) -> Vec2:
        """Where to head for next: along the cheapest route round everything the map
        shows so far (re-planned every `REPLAN_S`), keeping the shape's half-width off
        obstacles where there is room (followers go round what the shape does not clear);
        straight for the goal without a map.
        """
        grid = self.map
        if grid is None:
            return goal
        if t_s - self._planned_s >= REPLAN_S or self.carrot is None:
            self._planned_s = t_s
            planned = self._plan(grid, pose, goal)
            self.carrot = None if planned is None else planned.head_for
            self.points = () if planned is None else planned.points
        return self.carrot or goal

    def way_exists(self, pose: Pose2D, goal: Vec2, *, footprint_m: float) -> bool:
        """Whether the map shows a way to `goal` for a body `footprint_m` in radius (any
        way, however long; without a map it shows none).
        """
        grid = self.map
        return (
            grid is not None and self._plan(grid, pose, goal, footprint_m=footprint_m) is not None
        )

    def _plan(
        self, grid: OccupancyMap, pose: Pose2D, goal: Vec2, *, footprint_m: float = 0.0
    ) -> Planned | None:
        return grid.plan(
            pose.position, goal, keep_off_m=self.keep_off_m, ahead_m=ROUTE_AHEAD_M,
            footprint_m=footprint_m,
        )  # fmt: skip

    def forget_carrot(self) -> None:
        """Plan afresh next time (the robot stopped following the route)."""
        self.carrot = None
