"""Contacts in the simulated world: which robots' discs touch an obstacle (circle or
polygon) or another robot, and the collisions. A contact is recorded when it begins and
lasts until the robot has backed `CONTACT_RELEASE_M` away, so a robot pushing against a
wall is one collision, not one per sub-step.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from phalanx.core.config import WorldConfig
from phalanx.core.runlog import Collision
from phalanx.simulator.pairs import any_pair_within

FloatArray = npt.NDArray[np.float64]
_GRID_CELL_M = 1.0
CONTACT_RELEASE_M = 0.05
# `none_within`'s margin: distances of a few km carry rounding of about 1e-12 m.
_NONE_WITHIN_MARGIN_M = 1e-6


@dataclass(frozen=True)
class Edges:
    """The polygons' edges as arrays: from (ax, ay) to (bx, by), and whose each is."""

    ax: FloatArray
    ay: FloatArray
    bx: FloatArray
    by: FloatArray
    owner: npt.NDArray[np.intp]  # polygon index of each edge


def polygon_edges(world: WorldConfig) -> Edges:
    """Every edge of the world's polygons."""
    ax, ay, bx, by, owner = [], [], [], [], []
    for i, poly in enumerate(world.polygons):
        pts = poly.vertices_m
        for (x0, y0), (x1, y1) in zip(pts, pts[1:] + pts[:1], strict=True):
            ax.append(x0)
            ay.append(y0)
            bx.append(x1)
            by.append(y1)
            owner.append(i)
    arr = np.array
    return Edges(
        arr(ax, float), arr(ay, float), arr(bx, float), arr(by, float), arr(owner, dtype=np.intp)
    )


def _inside_polygon(px: float, py: float, pts: Sequence[tuple[float, float]]) -> bool:
    inside = False
    for (x0, y0), (x1, y1) in zip(pts, [*pts[1:], pts[0]], strict=True):
        if (y0 > py) != (y1 > py) and px < x0 + (py - y0) * (x1 - x0) / (y1 - y0):
            inside = not inside
    return inside


def _segment_distance(px: float, py: float, e: Edges) -> FloatArray:
    ex, ey = e.bx - e.ax, e.by - e.ay
    length2 = np.maximum(ex * ex + ey * ey, 1e-12)
    t = np.clip(((px - e.ax) * ex + (py - e.ay) * ey) / length2, 0.0, 1.0)
    return np.asarray(np.hypot(e.ax + t * ex - px, e.ay + t * ey - py), dtype=np.float64)


class Contacts:
    """The contacts of a fleet of discs (robot ids by index in `ids`, which the world
    appends to as robots are added) with the world's obstacles and with each other.
    """

    def __init__(
        self, config: WorldConfig, circles: FloatArray, edges: Edges, ids: list[str]
    ) -> None:
        self.config, self.circles, self.edges, self.ids = config, circles, edges, ids
        self.collisions: list[Collision] = []
        self.under_way: set[tuple[str, str]] = set()  # (robot id, other) touching now

    def record(self, i: int, other: str, t_s: float) -> None:
        """Robot `i` touches `other` at `t_s`: a collision if the contact is new."""
        rid = self.ids[i]
        if (rid, other) not in self.under_way:
            self.collisions.append(Collision(round(t_s, 9), rid, other))

    def settle(
        self, touching: list[tuple[int, str]], x: FloatArray, y: FloatArray, radius: float
    ) -> None:
        """After a sub-step: contacts backed away from end, the new ones are under way."""
        if self.under_way:  # (none under way, the usual case: nothing to release)
            loose = self.touching(x, y, radius + CONTACT_RELEASE_M)
            self.under_way &= {(self.ids[i], o) for i, o in loose}
        self.under_way |= {(self.ids[i], o) for i, o in touching}

    def none_within(self, x: FloatArray, y: FloatArray, radius: float, travel_m: float) -> bool:
        """Whether no contact can begin or end while every robot (a disc of `radius` at
        x, y) moves at most `travel_m`: none under way, no polygons (those are checked
        sub-step by sub-step), and every robot further than `travel_m` (plus a margin far
        wider than rounding) from touching a circle, and twice that from another robot.
        The world then skips the contact checks of that step's sub-steps.
        """
        if self.under_way or self.edges.ax.size:
            return False
        gap_m = travel_m + _NONE_WITHIN_MARGIN_M
        c = self.circles
        if len(c):
            d = np.hypot(x[:, None] - c[:, 0], y[:, None] - c[:, 1])
            if bool((d < c[:, 2] + (radius + gap_m)).any()):
                return False
        return not any_pair_within(x, y, 2.0 * (radius + gap_m))

    def touching(self, x: FloatArray, y: FloatArray, radius: float) -> list[tuple[int, str]]:
        """(robot index, other) for every contact of discs of `radius` at x, y."""
        found: list[tuple[int, str]] = []
        if len(self.circles):
            d = np.hypot(x[:, None] - self.circles[:, 0], y[:, None] - self.circles[:, 1])
            for i, k in zip(*np.nonzero(d < self.circles[:, 2] + radius), strict=True):
                found.append((int(i), f"obstacle:{int(k)}"))
        if self.edges.ax.size:
            found += self._polygon_contacts(x, y, radius)
        found += self._robot_contacts(x, y, radius)
        return found

    def _polygon_contacts(
        self, x: FloatArray, y: FloatArray, radius: float
    ) -> list[tuple[int, str]]:
        found = []
        offset = len(self.config.circles)
        for i in range(len(x)):
            near = _segment_distance(float(x[i]), float(y[i]), self.edges) < radius
            owners = set(self.edges.owner[near].tolist())
            for k, poly in enumerate(self.config.polygons):
                if k in owners or _inside_polygon(float(x[i]), float(y[i]), poly.vertices_m):
                    found.append((i, f"obstacle:{offset + k}"))
        return found

    def _robot_contacts(self, x: FloatArray, y: FloatArray, radius: float) -> list[tuple[int, str]]:
        if not any_pair_within(x, y, 2 * radius):
            return []  # the usual case, settled without building the grid
        cells: dict[tuple[int, int], list[int]] = {}
        for i, key in enumerate(
            zip(
                (x // _GRID_CELL_M).astype(int).tolist(),
                (y // _GRID_CELL_M).astype(int).tolist(),
                strict=True,
            )
        ):
            cells.setdefault(key, []).append(i)
        found = []
        for (cx, cy), members in cells.items():
            near = [
                j
                for dx in (-1, 0, 1)
                for dy in (-1, 0, 1)
                for j in cells.get((cx + dx, cy + dy), ())
            ]
            for i in members:
                for j in near:
                    if i != j and math.hypot(x[i] - x[j], y[i] - y[j]) < 2 * radius:
                        found.append((i, self.ids[j]))
        return found
