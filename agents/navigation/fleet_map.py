"""The fleet's shared map: one occupancy map that every robot's sonar feeds.

Each robot turns its masked sonar reading into a `Scan` (where it was taken, the
ranges, which are echoes of obstacles) and shares it (over Zenoh on
`robot/<id>/scan`; in the batch runner directly). At the start of a step a robot adds
every scan of the fleet it has not added yet, its own included, oldest first and in the
formation's order within a step: robots that heard the same scans hold the same map,
whichever process they run in (the batch runner gives all its robots one map object,
and each scan is added once). A prior map (`phalanx.core.mapfile`) is where it starts.

A robot masks the formation's robots out of its own reading where the shape expects
them (`phalanx.agents.masking`), and the robot it tracks where its state says. A robot
that is neither (sliding to a new slot, going round an obstacle) is an echo like an
obstacle's. The map knows better: every scan says where its robot was. An echo whose arc
passes within another robot's disc (its radius and `FLEET_MASK_M`), where that robot's
latest scan puts it (taken within `FLEET_FRESH_S` of the echo), is that robot, and is
not added; its beam is still seen free up to it, and no further.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import numpy as np

from phalanx.agents.navigation.grid import OccupancyMap, Reading
from phalanx.agents.perception import BoolArray, FloatArray, SonarGeometry
from phalanx.core.geometry import Pose2D, Vec2
from phalanx.core.mapfile import GridMap
from phalanx.core.peers import Scan

# An echo whose arc passes this close to another robot's body, where that robot's latest
# scan puts it, is that robot: the place is the robot's own estimate, as the tracked
# robot's state is (`masking.TRACKED_MASK_M`), and may be a step old.
FLEET_MASK_M = 0.15
# Where a robot scanned from counts for echoes at most this long before or after (s): a
# robot moves less than 0.2 m in it.
FLEET_FRESH_S = 0.25


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
        self.latest: dict[str, Scan] = {}  # robot -> its latest scan
        self.robot_echoes = 0  # echoes found to be another robot of the fleet

    def add(self, scans: Iterable[Scan]) -> None:
        """Add the scans not added yet (oldest first, then in the formation's order)."""
        fresh = [s for s in scans if s.stamp_s > self.added.get(s.robot_id, -np.inf) and s.ranges_m]
        if not fresh:  # (every robot but the first to add a step's scans)
            return
        fresh.sort(key=lambda s: (s.stamp_s, self.rank.get(s.robot_id, len(self.rank))))
        for scan in fresh:
            latest = self.latest.get(scan.robot_id)
            if latest is None or scan.stamp_s >= latest.stamp_s:
                self.latest[scan.robot_id] = scan
        self.map.update_many(self.sonar, self._readings(fresh, self._obstacle_echoes(fresh)))

    def _readings(self, fresh: list[Scan], echoes: list[BoolArray]) -> Iterator[Reading]:
        """The scans as the map's readings (with `echoes`), each counted as added once
        the map has taken it (as it asks for the next one; one it fails on is not).
        """
        for scan, echo in zip(fresh, echoes, strict=True):
            if scan.stamp_s <= self.added.get(scan.robot_id, -np.inf):
                continue  # (two of one robot in one batch: the first counts)
            yield scan.pose, scan.ranges_m, echo
            self.added[scan.robot_id] = scan.stamp_s
            self.scans_added += 1
            self.robot_echoes += sum(scan.echo) - int(np.count_nonzero(echo))

    def _obstacle_echoes(self, scans: list[Scan]) -> list[BoolArray]:
        """Each scan's echoes less those whose arc meets another robot of the fleet
        where its latest scan puts it, all scans in one pass (a ring the map cannot take
        is left as it is).
        """
        echoes = [np.asarray(s.echo, dtype=bool) for s in scans]
        units = self.sonar.unit_x_m.size
        rows = [i for i, s in enumerate(scans) if len(s.ranges_m) == units == len(s.echo)]
        if not rows or len(self.latest) < 2:
            return echoes
        heard = [scans[i] for i in rows]
        index = {r: j for j, r in enumerate(self.latest)}
        robots = np.array([(s.stamp_s, s.x_m, s.y_m) for s in self.latest.values()])
        poses = np.array([(s.stamp_s, s.x_m, s.y_m, s.theta_rad) for s in heard])
        r = np.array([s.ranges_m for s in heard])
        dx, dy = robots[:, 1] - poses[:, 1:2], robots[:, 2] - poses[:, 2:3]  # (scan, robot)
        sonar, radius_m = self.sonar, self.sonar.radius_m + FLEET_MASK_M
        # An echo at range r can be a robot only if the robot's centre is within r, give
        # or take the radius and `mount_m` (its transducer's furthest from where the scan
        # was taken), of that place: the (scan, robot) pairs with no such echo are left
        # out before any arc is worked out (the bound a hair wider, so that rounding
        # leaves out no arc that meets).
        apart = np.abs(r[:, None, :] - np.hypot(dx, dy)[..., None])
        heard_echo = np.array([echoes[i] for i in rows])[:, None, :]
        maybe = (apart < 1.001 * (sonar.mount_m + radius_m)) & heard_echo
        near = maybe.any(axis=2) & (np.abs(robots[:, 0] - poses[:, :1]) <= FLEET_FRESH_S)
        near[np.arange(len(heard)), [index[s.robot_id] for s in heard]] = False
        scan, robot = np.nonzero(near)
        if not scan.size:
            return echoes
        # where the robot is in the scan's body frame (`Pose2D.to_body`), a pair a row
        theta = poses[scan, 3]
        c, s_ = np.cos(theta), np.sin(theta)
        px, py = dx[scan, robot], dy[scan, robot]
        cx, cy = (c * px + s_ * py)[:, None], (c * py - s_ * px)[:, None]
        met = np.zeros(r.shape, dtype=bool)
        sonar.arcs_met(r, scan, (cx, cy), radius_m, sonar.nearest_dirs(cx, cy), met)
        for k in np.unique(scan).tolist():
            i = rows[k]
            echoes[i] = echoes[i] & ~met[k]
        return echoes


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
