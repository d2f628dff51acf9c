"""Contacts in the simulated world: which robots' discs touch an obstacle (circle or
polygon) or another robot, and the collisions. A contact is recorded when it begins and
lasts until the robot has backed `CONTACT_RELEASE_M` away, so a robot pushing against a
wall is one collision, not one per sub-step.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

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
# Up to this many robots, `near_walls` works in plain floats (cheaper than numpy's calls).
_FEW_ROBOTS = 12


@dataclass(frozen=True)
class Edges:
    """The polygons' edges as arrays: from (ax, ay) to (bx, by), and whose each is."""

    ax: FloatArray
    ay: FloatArray
    bx: FloatArray
    by: FloatArray
    owner: npt.NDArray[np.intp]  # polygon index of each edge

    @cached_property
    def spans(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Each edge's (x, y) extent from a to b and its squared length (at least 1e-12),
        worked out once for the run.
        """
        ex, ey = self.bx - self.ax, self.by - self.ay
        return ex, ey, np.maximum(ex * ex + ey * ey, 1e-12)


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
    ex, ey, length2 = e.spans
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
        # each polygon's bounding box: lowest x, y and highest x, y, a column each
        self._box_list: list[tuple[float, float, float, float]] = [
            (min(xs), min(ys), max(xs), max(ys))
            for xs, ys in (zip(*p.vertices_m, strict=True) for p in config.polygons)
        ]
        self._boxes = np.array(self._box_list, dtype=np.float64).reshape(-1, 4).T.copy()

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

    def near_walls(self, x: FloatArray, y: FloatArray, radius: float, travel_m: float) -> list[int]:
        """The robots (discs of `radius` at x, y) that may touch a polygon while they move
        at most `travel_m`: those within `travel_m` (plus `none_within`'s margin) of
        touching a polygon's bounding box. Any other robot is outside every polygon and
        stays further than `radius` from its edges, so its contacts with the polygons
        need no check within that move.
        """
        if not self._box_list:
            return []
        reach_m = radius + travel_m + _NONE_WITHIN_MARGIN_M
        if len(x) <= _FEW_ROBOTS:
            return self._near_boxes(x.tolist(), y.tolist(), reach_m)
        x0, y0, x1, y1 = self._boxes
        px, py = x[:, None], y[:, None]
        # how far each robot is from each box, along x and along y (0 within its span)
        out_x = np.maximum(np.maximum(x0 - px, px - x1), 0.0)
        out_y = np.maximum(np.maximum(y0 - py, py - y1), 0.0)
        near = out_x * out_x + out_y * out_y <= reach_m * reach_m
        rows: list[int] = np.flatnonzero(near.any(axis=1)).tolist()
        return rows

    def _near_boxes(self, x: list[float], y: list[float], reach_m: float) -> list[int]:
        """`near_walls` in plain floats (the same arithmetic), for a few robots."""
        rows = []
        for i, (px, py) in enumerate(zip(x, y, strict=True)):
            for x0, y0, x1, y1 in self._box_list:
                out_x, out_y = max(max(x0 - px, px - x1), 0.0), max(max(y0 - py, py - y1), 0.0)
                if out_x * out_x + out_y * out_y <= reach_m * reach_m:
                    rows.append(i)
                    break
        return rows

    def none_within(self, x: FloatArray, y: FloatArray, radius: float, travel_m: float) -> bool:
        """Whether no contact can begin or end while every robot (a disc of `radius` at
        x, y) moves at most `travel_m`: none under way, and every robot further than
        `travel_m` (plus a margin far wider than rounding) from touching a circle or a
        polygon's bounding box, and twice that from another robot. The world then skips
        the contact checks of that step's sub-steps.
        """
        if self.under_way or self.near_walls(x, y, radius, travel_m):
            return False
        gap_m = travel_m + _NONE_WITHIN_MARGIN_M
        c = self.circles
        if len(c):
            d = np.hypot(x[:, None] - c[:, 0], y[:, None] - c[:, 1])
            if bool((d < c[:, 2] + (radius + gap_m)).any()):
                return False
        return not any_pair_within(x, y, 2.0 * (radius + gap_m))

    def touching(
        self,
        x: FloatArray,
        y: FloatArray,
        radius: float,
        walls: Sequence[int] | None = None,
    ) -> list[tuple[int, str]]:
        """(robot index, other) for every contact of discs of `radius` at x, y; the
        polygons checked for robots `walls` only (None: every robot), those `near_walls`
        gave for a move that ends here.
        """
        found: list[tuple[int, str]] = []
        if len(self.circles):
            d = np.hypot(x[:, None] - self.circles[:, 0], y[:, None] - self.circles[:, 1])
            for i, k in zip(*np.nonzero(d < self.circles[:, 2] + radius), strict=True):
                found.append((int(i), f"obstacle:{int(k)}"))
        if self.edges.ax.size:
            rows = range(len(x)) if walls is None else walls
            found += self._polygon_contacts(x, y, radius, rows)
        found += self._robot_contacts(x, y, radius)
        return found

    def _polygon_contacts(
        self, x: FloatArray, y: FloatArray, radius: float, rows: Sequence[int]
    ) -> list[tuple[int, str]]:
        found = []
        offset = len(self.config.circles)
        for i in rows:
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
