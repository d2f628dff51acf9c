"""The fleet's shared map: one occupancy map that every robot's sonar feeds.

Each robot turns its masked sonar reading into a `Scan` (where it was taken, the
ranges, which are echoes of obstacles) and shares it (over Zenoh on
`robot/<id>/scan`; in the batch runner directly). At the start of a step a robot adds
every scan of the fleet it has not added yet, its own included, oldest first and in the
formation's order within a step: robots that heard the same scans hold the same map,
whichever process they run in (the batch runner gives all its robots one map object,
and each scan is added once). A prior map (`phalanx.core.mapfile`) is where it starts.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import numpy as np

from phalanx.agents.navigation.grid import OccupancyMap, Reading
from phalanx.agents.perception import BoolArray, FloatArray, SonarGeometry
from phalanx.core.geometry import Pose2D, Vec2
from phalanx.core.mapfile import GridMap
from phalanx.core.peers import Scan


class FleetMap:
    """An occupancy map fed by scans of many robots, each added once, in a fixed order."""

    def __init__(
        self,
        origin: Vec2,
        *,
        sonar: SonarGeometry,
        order: Iterable[str],
        prior: GridMap | None = None,
    ) -> None:
        self.map = OccupancyMap(origin)
        if prior is not None:
            self.map.load_prior(prior)
        self.sonar = sonar
        self.rank = {r: i for i, r in enumerate(order)}
        self.added: dict[str, float] = {}  # robot -> stamp of its last scan added
        self.scans_added = 0

    def add(self, scans: Iterable[Scan]) -> None:
        """Add the scans not added yet (oldest first, then in the formation's order)."""
        fresh = [s for s in scans if s.stamp_s > self.added.get(s.robot_id, -np.inf) and s.ranges_m]
        if not fresh:  # (every robot but the first to add a step's scans)
            return
        fresh.sort(key=lambda s: (s.stamp_s, self.rank.get(s.robot_id, len(self.rank))))
        self.map.update_many(self.sonar, self._readings(fresh))

    def _readings(self, fresh: list[Scan]) -> Iterator[Reading]:
        """The scans as the map's readings, each counted as added once the map has taken
        it (as it asks for the next one; one it fails on is not).
        """
        for scan in fresh:
            if scan.stamp_s <= self.added.get(scan.robot_id, -np.inf):
                continue  # (two of one robot in one batch: the first counts)
            yield scan.pose, scan.ranges_m, np.asarray(scan.echo, dtype=bool)
            self.added[scan.robot_id] = scan.stamp_s
            self.scans_added += 1


def scan_of(robot_id: str, t_s: float, pose: Pose2D, ranges: FloatArray, echo: BoolArray) -> Scan:
    """A reading as the scan a robot shares."""
    return Scan(
        robot_id,
        t_s,
        pose.x_m,
        pose.y_m,
        pose.theta_rad,
        # (`tolist` gives Python floats and bools)
        tuple(np.asarray(ranges, dtype=np.float64).tolist()),
        tuple(np.asarray(echo, dtype=bool).tolist()),
    )
