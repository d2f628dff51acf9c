"""A robot's memory of where obstacles are, from its own sonar ring, and a navigation
function over it: which way to go to reach a goal round everything seen so far.

The grid is coarse (0.5 m cells) and centred on where the robot started. Each echo
marks the cells of its beam's centre and edges at its range as hit; the cells its centre
ray crossed before that are seen free (hits decay when seen free again, so a robot that
drove away stops blocking the map). What was never seen is assumed free: the route is
optimistic and is re-planned as the map fills in.

The route is a wavefront (Dijkstra on the 8-connected grid, in numpy) from the goal over
the free cells, with obstacles grown by a clearance: the formation's half-width first,
so the whole shape fits, then the robot's own radius when the shape does not.
The reactive layer (`phalanx.agents.navigation.steering`) still decides the actual heading.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from phalanx.agents.perception import ARC_SPREAD_M, BoolArray, SonarGeometry
from phalanx.core.geometry import Pose2D, Vec2
from phalanx.core.mapfile import FREE, UNKNOWN, GridMap
from phalanx.core.mapfile import OCCUPIED as OCCUPIED_CELL

FloatArray = npt.NDArray[np.float64]
CELL_M = 0.5
HALF_SIZE_M = 40.0
HIT = 3  # evidence added by an echo, capped at MAX_EVIDENCE; a free sighting takes 1
MAX_EVIDENCE = 6
OCCUPIED = 2
FREE_REACH_M = 3.0  # a max-range reading clears its ray this far (specular misses exist)
MAP_RANGE_M = 3.0  # echoes further than this are not marked (too vague a place)
PLAN_MARGIN_M = 10.0
MAX_PATH_CELLS = 400
NEAR_COST = 4.0  # a cell near an obstacle costs this many free ones
UNREACHABLE = 1e9
_MOVES = tuple((dy, dx, math.hypot(dy, dx)) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx)


class OccupancyMap:
    """Evidence of obstacles on a grid in the world frame (SI units)."""

    def __init__(
        self, origin: Vec2, *, half_size_m: float = HALF_SIZE_M, cell_m: float = CELL_M
    ) -> None:
        self.cell_m = cell_m
        self.cells = round(2 * half_size_m / cell_m)
        self.x0_m = origin.x_m - half_size_m
        self.y0_m = origin.y_m - half_size_m
        self.evidence = np.zeros((self.cells, self.cells), dtype=np.int8)
        self.seen = np.zeros((self.cells, self.cells), dtype=bool)  # ever sensed (or known)

    def index(self, x_m: FloatArray, y_m: FloatArray) -> tuple[npt.NDArray[np.intp], ...]:
        """(row, column) of world points, and whether each lies on the grid."""
        col = np.floor((x_m - self.x0_m) / self.cell_m).astype(np.intp)
        row = np.floor((y_m - self.y0_m) / self.cell_m).astype(np.intp)
        inside = (col >= 0) & (col < self.cells) & (row >= 0) & (row < self.cells)
        return row, col, inside.astype(np.intp)

    def covers(self, point: Vec2) -> bool:
        """Whether `point` (world frame) lies on the grid."""
        col = math.floor((point.x_m - self.x0_m) / self.cell_m)
        row = math.floor((point.y_m - self.y0_m) / self.cell_m)
        return 0 <= col < self.cells and 0 <= row < self.cells

    def centre(self, row: int, col: int) -> Vec2:
        """World position of a cell's centre."""
        return Vec2(self.x0_m + (col + 0.5) * self.cell_m, self.y0_m + (row + 0.5) * self.cell_m)

    def update(
        self,
        pose: Pose2D,
        sonar: SonarGeometry,
        ranges_m: Sequence[float] | FloatArray,
        echo: BoolArray | None = None,
    ) -> None:
        """Add one reading taken at `pose`: the echoes `echo` marks (`sonar.echoes`: the
        formation's robots left out), every echo if not given.
        """
        ranges = np.asarray(ranges_m, dtype=np.float64)
        units = sonar.unit_x_m.size
        if ranges.size < units:
            return
        r = ranges[:units]
        if echo is None:
            echo = sonar.echoes(ranges)
        c, s = math.cos(pose.theta_rad), math.sin(pose.theta_rad)
        ox = pose.x_m + c * sonar.unit_x_m - s * sonar.unit_y_m
        oy = pose.y_m + s * sonar.unit_x_m + c * sonar.unit_y_m
        heading = pose.theta_rad + sonar.unit_heading_rad
        self._see_free(ox, oy, heading, np.where(echo, r - self.cell_m, FREE_REACH_M))
        near = echo & (r < MAP_RANGE_M)  # far echoes are too vague to remember
        half = np.minimum(sonar.half_beam_rad, np.arctan2(ARC_SPREAD_M, np.maximum(r, 1e-6)))
        for offset in (-1.0, 0.0, 1.0):
            angle = heading + offset * half
            hx, hy = ox + r * np.cos(angle), oy + r * np.sin(angle)
            self._add(hx[near], hy[near], HIT)

    def _see_free(
        self, ox: FloatArray, oy: FloatArray, heading: FloatArray, reach: FloatArray
    ) -> None:
        steps = np.arange(0.0, float(reach.max(initial=0.0)), self.cell_m / 2)
        if steps.size == 0:
            return
        along = steps[None, :]
        mask = along < reach[:, None]
        x = (ox[:, None] + along * np.cos(heading)[:, None])[mask]
        y = (oy[:, None] + along * np.sin(heading)[:, None])[mask]
        self._add(x, y, -1)

    def _add(self, x: FloatArray, y: FloatArray, amount: int) -> None:
        row, col, inside = self.index(x, y)
        keep = inside.astype(bool)
        row, col = row[keep], col[keep]
        if row.size == 0:
            return
        cells = np.unique(row * self.cells + col)
        flat = self.evidence.reshape(-1)
        flat[cells] = np.clip(flat[cells].astype(np.int16) + amount, 0, MAX_EVIDENCE)
        self.seen.reshape(-1)[cells] = True

    def load_prior(self, prior: GridMap) -> None:
        """Start from a known map: a cell holding any of its occupied cells is occupied
        (at full evidence, which sonar can still wear down), one holding only free cells
        is known free.
        """
        for which, evidence in ((FREE, 0), (OCCUPIED_CELL, MAX_EVIDENCE)):
            row, col, inside = self.index(*prior.centres(which))
            keep = inside.astype(bool)
            self.evidence[row[keep], col[keep]] = evidence
            self.seen[row[keep], col[keep]] = True

    def to_grid(self) -> GridMap:
        """The map as an occupancy grid (`phalanx.core.mapfile`): occupied, seen free,
        or never sensed.
        """
        cells = np.full(self.evidence.shape, UNKNOWN, dtype=np.int8)
        cells[self.seen] = FREE
        cells[self.occupied()] = OCCUPIED_CELL
        return GridMap(cells, self.cell_m, (self.x0_m, self.y0_m, 0.0))

    def occupied(self) -> npt.NDArray[np.bool_]:
        """Cells believed to hold an obstacle."""
        occupied: npt.NDArray[np.bool_] = self.evidence >= OCCUPIED
        return occupied

    def route(self, start: Vec2, goal: Vec2, *, keep_off_m: float, ahead_m: float) -> Vec2 | None:
        """Where to head for along the cheapest route from `start` to `goal` round every
        obstacle seen, cells within `keep_off_m` of one costing `NEAR_COST` times more (a
        route keeps that far off where there is room, and squeezes by where not): the
        furthest point of the route (the goal itself if it is) in plain sight over free
        cells, at least `ahead_m` along it; None if there is no route.
        """
        planned = self.plan(start, goal, keep_off_m=keep_off_m, ahead_m=ahead_m)
        return None if planned is None else planned[0]

    def plan(
        self,
        start: Vec2,
        goal: Vec2,
        *,
        keep_off_m: float,
        ahead_m: float,
        footprint_m: float = 0.0,
    ) -> tuple[Vec2, float] | None:
        """`route` for a footprint: cells nearer than `footprint_m` to an obstacle are
        closed (a shape that wide cannot pass there; the cells round `start` stay open,
        the robot is where it is). Where to head for, and the route's length (m, each
        cell weighted by its cost); None if there is no route.
        """
        window = self._window(start, goal)
        occupied = self.occupied()[window]
        blocked = _grow(occupied, _cells_within(footprint_m, self.cell_m))
        near = _grow(occupied, math.ceil(keep_off_m / self.cell_m - 0.5))
        cost = np.where(near, NEAR_COST, 1.0)
        (r0, c0), (rg, cg) = self._cell(start, window), self._cell(goal, window)
        if not _on(blocked, rg, cg) or not _on(blocked, r0, c0):
            return None
        if footprint_m > 0.0 and blocked[rg, cg]:
            return None
        blocked[rg, cg] = False
        reach = _cells_within(footprint_m, self.cell_m)
        if reach:
            rows, cols = np.ogrid[: blocked.shape[0], : blocked.shape[1]]
            round_start = (rows - r0) ** 2 + (cols - c0) ** 2 <= reach * reach
            blocked &= ~round_start | occupied  # where it stands it may move off from
        blocked[r0, c0] = False  # the robot's own cell: it is where it is
        dist = _wavefront(blocked, cost, rg, cg)
        if dist[r0, c0] >= UNREACHABLE:
            return None
        length_m = float(dist[r0, c0]) * self.cell_m
        offset = (window[0].start, window[1].start)
        path = [(r0, c0)]
        while path[-1] != (rg, cg) and len(path) < MAX_PATH_CELLS:
            path.append(_downhill(dist, *path[-1]))
        points = [self.centre(r + offset[0], c + offset[1]) for r, c in path[1:]] + [goal]
        minimum = min(len(points) - 1, max(0, round(ahead_m / self.cell_m) - 1))
        for point in reversed(points[minimum:]):
            if self._in_sight(start, point, blocked, offset):
                return point, length_m
        return points[minimum], length_m

    def clear_within(self, point: Vec2, radius_m: float) -> bool:
        """Whether no cell within `radius_m` of `point` is believed occupied."""
        reach = math.ceil(radius_m / self.cell_m) + 1
        row, col, _ = self.index(np.array([point.x_m]), np.array([point.y_m]))
        r0, c0 = int(row[0]), int(col[0])
        rows = slice(max(0, r0 - reach), max(0, r0 + reach + 1))
        cols = slice(max(0, c0 - reach), max(0, c0 + reach + 1))
        hit_r, hit_c = np.nonzero(self.occupied()[rows, cols])
        if hit_r.size == 0:
            return True
        x = self.x0_m + (hit_c + cols.start + 0.5) * self.cell_m
        y = self.y0_m + (hit_r + rows.start + 0.5) * self.cell_m
        near = np.hypot(x - point.x_m, y - point.y_m) - self.cell_m / 2
        return bool((near >= radius_m).all())

    def _in_sight(
        self, a: Vec2, b: Vec2, blocked: npt.NDArray[np.bool_], offset: tuple[int, int]
    ) -> bool:
        """Whether the segment a-b crosses only free cells of `blocked` (a window)."""
        steps = max(2, math.ceil((b - a).norm() / (self.cell_m / 2)))
        f = np.linspace(0.0, 1.0, steps)
        row, col, _ = self.index(a.x_m + f * (b.x_m - a.x_m), a.y_m + f * (b.y_m - a.y_m))
        row, col = row - offset[0], col - offset[1]
        h, w = blocked.shape
        inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
        return bool(inside.all()) and not bool(blocked[row, col].any())

    def _window(self, a: Vec2, b: Vec2) -> tuple[slice, slice]:
        xs, ys = (a.x_m, b.x_m), (a.y_m, b.y_m)
        row, col, _ = self.index(
            np.array([min(xs) - PLAN_MARGIN_M, max(xs) + PLAN_MARGIN_M]),
            np.array([min(ys) - PLAN_MARGIN_M, max(ys) + PLAN_MARGIN_M]),
        )
        clip = np.clip
        rows = slice(int(clip(row[0], 0, self.cells)), int(clip(row[1] + 1, 0, self.cells)))
        cols = slice(int(clip(col[0], 0, self.cells)), int(clip(col[1] + 1, 0, self.cells)))
        return rows, cols

    def _cell(self, p: Vec2, window: tuple[slice, slice]) -> tuple[int, int]:
        row, col, _ = self.index(np.array([p.x_m]), np.array([p.y_m]))
        return int(row[0]) - window[0].start, int(col[0]) - window[1].start


def _cells_within(distance_m: float, cell_m: float) -> int:
    """How many cells a disc of `distance_m` round a cell's centre reaches past it."""
    return max(0, math.ceil(distance_m / cell_m - 0.5)) if distance_m > 0.0 else 0


def _on(grid: npt.NDArray[np.bool_], row: int, col: int) -> bool:
    h, w = int(grid.shape[0]), int(grid.shape[1])
    return 0 <= row < h and 0 <= col < w


def _moved(out: npt.NDArray[Any], a: npt.NDArray[Any], dy: int, dx: int) -> None:
    """out[r, c] = a[r - dy, c - dx] where both exist."""
    h, w = a.shape
    out[max(dy, 0) : h + min(dy, 0), max(dx, 0) : w + min(dx, 0)] = a[
        max(-dy, 0) : h + min(-dy, 0), max(-dx, 0) : w + min(-dx, 0)
    ]


def _shift_cost(a: FloatArray, dy: int, dx: int) -> FloatArray:
    out = np.full_like(a, UNREACHABLE)
    _moved(out, a, dy, dx)
    return out


def _grow(occupied: npt.NDArray[np.bool_], cells: int) -> npt.NDArray[np.bool_]:
    """Obstacles grown by `cells` (a disc)."""
    grown = occupied.copy()
    for dy in range(-cells, cells + 1):
        for dx in range(-cells, cells + 1):
            if (dy or dx) and dy * dy + dx * dx <= cells * cells:
                shifted = np.zeros_like(occupied)
                _moved(shifted, occupied, dy, dx)
                grown |= shifted
    return grown


def _wavefront(blocked: npt.NDArray[np.bool_], cost: FloatArray, row: int, col: int) -> FloatArray:
    """Cost to reach (row, col) from every free cell: 8-connected moves, each costing its
    length (in cells) times the cost of the cell moved into.
    """
    dist = np.full(blocked.shape, UNREACHABLE)
    dist[row, col] = 0.0
    for _ in range(8 * sum(blocked.shape)):
        best = dist
        for dy, dx, step in _MOVES:
            best = np.minimum(best, _shift_cost(dist, dy, dx) + step * cost)
        best[blocked] = UNREACHABLE
        best[row, col] = 0.0
        if np.array_equal(best, dist):
            break
        dist = best
    return dist


def _downhill(dist: FloatArray, row: int, col: int) -> tuple[int, int]:
    h, w = dist.shape
    best = (row, col)
    for dy, dx, _ in _MOVES:
        r, c = row + dy, col + dx
        if 0 <= r < h and 0 <= c < w and dist[r, c] < dist[best]:
            best = (r, c)
    return best
