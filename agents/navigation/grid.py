"""A robot's memory of where obstacles are, from its own sonar ring, and a navigation
function over it: which way to go to reach a goal round everything seen so far.

The grid is coarse (0.5 m cells) and centred on where the robot started. An echo came
from somewhere on its beam's arc at its range, most likely near the beam's axis: it adds
`HIT` to the cell on the axis and `EDGE_HIT` to the cells at the beam's edges. The cells
its axis crossed before that are seen free, each taking one away: a robot that drove
away stops blocking the map, and an edge's guess wears off at the first clear view. A
beam that met one of the formation's robots (masked out: no echo) is seen free only up
to that robot, what lies behind it unseen; a beam that met nothing is seen free for
`FREE_REACH_M`. What was never seen is assumed free: the route is optimistic and is
re-planned as the map fills in.

The route is a wavefront (Dijkstra on the 8-connected grid, in numpy) from the goal over
the free cells, with obstacles grown by a clearance: the formation's half-width first,
so the whole shape fits, then the robot's own radius when the shape does not.
The reactive layer (`phalanx.agents.navigation.steering`) still decides the actual heading.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Sequence
from types import ModuleType
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from phalanx.agents.perception import ARC_SPREAD_M, BoolArray, SonarGeometry
from phalanx.core.compiled import kernels
from phalanx.core.geometry import Pose2D, Vec2
from phalanx.core.mapfile import FREE, UNKNOWN, GridMap
from phalanx.core.mapfile import OCCUPIED as OCCUPIED_CELL

FloatArray = npt.NDArray[np.float64]
Window = tuple[slice, slice]  # rows and columns of the grid a plan works over
Cell = tuple[int, int]  # (row, column) in a window
# A sonar reading to add: where it was taken, its ranges (m), its echoes (None: every one).
Reading = tuple[Pose2D, Sequence[float] | FloatArray, BoolArray | None]
CELL_M = 0.5
HALF_SIZE_M = 40.0
HIT = 3  # evidence added by an echo on its beam's axis, capped at MAX_EVIDENCE
EDGE_HIT = 1  # added at its beam's edges; a free sighting takes 1
MAX_EVIDENCE = 6
OCCUPIED = 2
FREE_REACH_M = 3.0  # a max-range reading clears its ray this far (specular misses exist)
MAP_RANGE_M = 3.0  # echoes further than this are not marked (too vague a place)
PLAN_MARGIN_M = 10.0
MAX_PATH_CELLS = 400
SIGHT_BATCH = 16  # route points looked at together for the furthest in sight
NEAR_COST = 4.0  # a cell near an obstacle costs this many free ones
UNREACHABLE = 1e9
_STRAIGHT, _DIAGONAL = math.hypot(0, 1), math.hypot(1, 1)  # a move's length (cells)
# Where an echo marks its beam at its range (edge, axis, edge: a fraction of the half
# beam's angle off the axis) and the evidence it adds there.
_ARC = ((-1.0, EDGE_HIT), (0.0, HIT), (1.0, EDGE_HIT))
_ARC_OFFSETS = np.array([[offset] for offset, _ in _ARC])
# The compiled update and wavefront (`phalanx.core.compiled`), where numba is installed.
KERNELS = "phalanx.agents.navigation.grid_kernels"
_MOVES = tuple((dy, dx, math.hypot(dy, dx)) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx)


class Planned(NamedTuple):
    """A route planned over the map."""

    head_for: Vec2  # the furthest point along it in plain sight (world frame)
    length_m: float  # each cell weighted by its cost
    points: tuple[Vec2, ...]  # the cells' centres along it from the start's, then the goal


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
        # The compiled update's: which marking last changed each cell, and how many so far.
        self._stamp: npt.NDArray[np.int64] | None = None
        self._marks = 0

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
        self.update_many(sonar, [(pose, ranges_m, echo)])

    def update_many(self, sonar: SonarGeometry, readings: Iterable[Reading]) -> None:
        """`update` with each reading (pose, ranges, echoes) in turn, worked out together.
        One that raises (its echoes do not fit its ranges) leaves those before it added.
        """
        taken: list[tuple[Pose2D, FloatArray, BoolArray]] = []
        units = sonar.unit_x_m.size
        try:
            for pose, ranges_m, echo in readings:
                ranges = np.asarray(ranges_m, dtype=np.float64)
                if ranges.size < units:
                    continue
                r = ranges[:units]
                if echo is None:
                    echo = sonar.echoes(ranges)
                elif not (isinstance(echo, np.ndarray) and echo.shape == r.shape):
                    echo = np.broadcast_to(echo, r.shape)
                taken.append((pose, r, echo))
        finally:
            if taken:
                self._add_readings(sonar, taken)

    def _add_readings(
        self, sonar: SonarGeometry, readings: Sequence[tuple[Pose2D, FloatArray, BoolArray]]
    ) -> None:
        """Each reading's rays seen free, then its echoes, reading after reading (the
        cells of all of them found in one pass; the compiled loop's, where numba is).
        """
        ox, oy, heading = _sonar_rays([pose for pose, _, _ in readings], sonar)
        r = _rows([reading[1] for reading in readings])
        echo = _rows([reading[2] for reading in readings])
        # a beam that met something is free up to it, whether it met an obstacle or one
        # of the formation's robots (masked out: no echo here, but no clear view past it)
        reach = np.where(sonar.ranged(r), r - self.cell_m, FREE_REACH_M)
        near = echo & (r < MAP_RANGE_M)  # far echoes are too vague to remember
        compiled = kernels(KERNELS)
        if compiled is not None:
            self._add_compiled(compiled, sonar, (ox, oy, heading, reach), r, near)
            return
        free_x, free_y, free_counts = self._free_points(ox, oy, heading, reach)
        arc_x, arc_y = _arc_points(sonar, (ox, oy, heading), r, near)
        cells = self._cells(np.concatenate((free_x, arc_x)), np.concatenate((free_y, arc_y)))
        # (as a rule every cell is on the grid, and there is none to drop)
        on_grid = _as_they_are if cells.size and cells.min() >= 0 else _on_grid
        free_cells, arc_cells = cells[: free_x.size], cells[free_x.size :]
        free_at = arc_at = 0
        for free_count, echoes in zip(free_counts.tolist(), near.sum(axis=1).tolist(), strict=True):
            self._mark(on_grid(free_cells[free_at : free_at + free_count]), -1)
            free_at += free_count
            if not echoes:
                continue
            # each echo marks its beam's right edge, centre and left edge at its range,
            # one after the other (a cell two of them fall in gains both)
            for _, amount in _ARC:
                self._mark(on_grid(arc_cells[arc_at : arc_at + echoes]), amount)
                arc_at += echoes
        self.seen.reshape(-1)[on_grid(cells)] = True

    def _add_compiled(
        self,
        compiled: ModuleType,
        sonar: SonarGeometry,
        rays: tuple[FloatArray, FloatArray, FloatArray, FloatArray],
        r: FloatArray,
        near: BoolArray,
    ) -> None:
        """`_add_readings` by the compiled loop (`grid_kernels`), from the cosines and
        sines numpy works out (the loop's own could differ from numpy's in the last bit).
        """
        ox, oy, heading, reach = rays
        if self._stamp is None:
            self._stamp = np.zeros(self.evidence.size, dtype=np.int64)
        steps = np.arange(0.0, float(reach.max(initial=0.0)), self.cell_m / 2)
        arc_c = arc_s = np.empty((0, 0, 0))
        if near.any():
            angle = _arc_angles(sonar, heading, r)
            arc_c, arc_s = np.cos(angle), np.sin(angle)
        self._marks = compiled.add_readings(
            self.evidence.reshape(-1), self.seen.reshape(-1), self._stamp, self._marks,
            _TABLES, (self.x0_m, self.y0_m, self.cell_m, self.cells),
            (ox, oy, np.cos(heading), np.sin(heading), reach), steps,
            (r, near, arc_c, arc_s),
        )  # fmt: skip

    def _free_points(
        self, ox: FloatArray, oy: FloatArray, heading: FloatArray, reach: FloatArray
    ) -> tuple[FloatArray, FloatArray, npt.NDArray[np.intp]]:
        """Points every half cell along each ray from (ox, oy) short of its `reach`, and
        how many of them each reading (row) has.
        """
        steps = np.arange(0.0, float(reach.max(initial=0.0)), self.cell_m / 2)
        along = steps[None, None, :]
        mask = along < reach[:, :, None]
        x = (ox[:, :, None] + along * np.cos(heading)[:, :, None])[mask]
        y = (oy[:, :, None] + along * np.sin(heading)[:, :, None])[mask]
        return x, y, mask.sum(axis=(1, 2))

    def _add(self, x: FloatArray, y: FloatArray, amount: int) -> None:
        """Add `amount` to the evidence of every cell holding one of the points (once a
        cell, however many fall in it; clipped to 0 to `MAX_EVIDENCE`), and mark it seen.
        """
        cells = self._cells(x, y)
        cells = cells[cells >= 0]
        self._mark(cells, amount)
        self.seen.reshape(-1)[cells] = True

    def _cells(self, x: FloatArray, y: FloatArray) -> npt.NDArray[np.intp]:
        """Flat index of the cell each world point lies in, -1 for one off the grid
        (`index`, as one number).
        """
        n = self.cells
        col = np.floor((x - self.x0_m) / self.cell_m).astype(np.intp)
        row = np.floor((y - self.y0_m) / self.cell_m).astype(np.intp)
        # (a negative index, seen unsigned, is past the grid's end too)
        inside = (col.view(np.uintp) < n) & (row.view(np.uintp) < n)
        return np.where(inside, row * n + col, -1)

    def _mark(self, cells: npt.NDArray[np.intp], amount: int) -> None:
        """Add `amount` to the evidence of `cells` (flat indices), clipped to 0 to
        `MAX_EVIDENCE`: a cell listed twice gets it once (both writes are of the value
        read before either).
        """
        flat = self.evidence.reshape(-1)
        flat[cells] = _added(amount)[flat[cells].view(np.uint8)]

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

    def occupied(self, window: Window = (slice(None), slice(None))) -> npt.NDArray[np.bool_]:
        """Cells believed to hold an obstacle (of `window`; the whole grid by default)."""
        occupied: npt.NDArray[np.bool_] = self.evidence[window] >= OCCUPIED
        return occupied

    def route(self, start: Vec2, goal: Vec2, *, keep_off_m: float, ahead_m: float) -> Vec2 | None:
        """Where to head for along the cheapest route from `start` to `goal` round every
        obstacle seen, cells within `keep_off_m` of one costing `NEAR_COST` times more (a
        route keeps that far off where there is room, and squeezes by where not): the
        furthest point of the route (the goal itself if it is) in plain sight over free
        cells, at least `ahead_m` along it; None if there is no route.
        """
        planned = self.plan(start, goal, keep_off_m=keep_off_m, ahead_m=ahead_m)
        return None if planned is None else planned.head_for

    def plan(
        self,
        start: Vec2,
        goal: Vec2,
        *,
        keep_off_m: float,
        ahead_m: float,
        footprint_m: float = 0.0,
    ) -> Planned | None:
        """`route` for a footprint: cells nearer than `footprint_m` to an obstacle are
        closed (a shape that wide cannot pass there; the cells round `start` stay open,
        the robot is where it is). Where to head for, the route's length and its points;
        None if there is no route.
        """
        spread = self._spread(start, goal, keep_off_m=keep_off_m, footprint_m=footprint_m)
        if spread is None:
            return None
        dist, blocked, window, (r0, c0), (rg, cg) = spread
        length_m = float(dist[r0, c0]) * self.cell_m
        offset = (window[0].start, window[1].start)
        path = [(r0, c0)]
        while path[-1] != (rg, cg) and len(path) < MAX_PATH_CELLS:
            path.append(_downhill(dist, *path[-1]))
        points = [self.centre(r + offset[0], c + offset[1]) for r, c in path[1:]] + [goal]
        minimum = min(len(points) - 1, max(0, round(ahead_m / self.cell_m) - 1))
        head_for = self._furthest_in_sight(start, points[minimum:], blocked, offset)
        return Planned(head_for, length_m, tuple(points))

    def route_length_m(self, start: Vec2, goal: Vec2, *, footprint_m: float) -> float | None:
        """The length of `plan`'s route for `footprint_m` (no cell near an obstacle
        costing more), without working out where to head for; None if there is none.
        """
        spread = self._spread(start, goal, keep_off_m=0.0, footprint_m=footprint_m)
        if spread is None:
            return None
        dist, _, _, (r0, c0), _ = spread
        return float(dist[r0, c0]) * self.cell_m

    def fewest_m(self, start: Vec2, goal: Vec2) -> float:
        """A length no route from `start` to `goal` (`plan`'s, `route_length_m`'s) comes
        under (m): the fewest moves between their cells, each move costing at least its
        length; a hair less, so that the floats of a route's sum never come under it.
        """
        row, col, _ = self.index(np.array([start.x_m, goal.x_m]), np.array([start.y_m, goal.y_m]))
        rows, cols = abs(int(row[0]) - int(row[1])), abs(int(col[0]) - int(col[1]))
        moves = (max(rows, cols) - min(rows, cols)) * _STRAIGHT + min(rows, cols) * _DIAGONAL
        return moves * self.cell_m * (1.0 - 1e-9)

    def _spread(
        self, start: Vec2, goal: Vec2, *, keep_off_m: float, footprint_m: float
    ) -> tuple[FloatArray, npt.NDArray[np.bool_], Window, Cell, Cell] | None:
        """`plan`'s wavefront from the goal over the window holding `start` and `goal`:
        the cost to go from each cell, the cells closed, the window, the start's and the
        goal's cells; None if the start is not reached.
        """
        window = self._window(start, goal)
        occupied = self.occupied(window)
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
        dist = _wavefront(blocked, cost, rg, cg, start=(r0, c0))
        if dist[r0, c0] >= UNREACHABLE:
            return None
        return dist, blocked, window, (r0, c0), (rg, cg)

    def clear_within(self, point: Vec2, radius_m: float) -> bool:
        """Whether no cell within `radius_m` of `point` is believed occupied."""
        return bool(self.clear_of([point], radius_m)[0])

    def clear_of(self, points: Sequence[Vec2], radius_m: float) -> BoolArray:
        """`clear_within` for each of `points`, worked out together."""
        px = np.array([p.x_m for p in points])
        py = np.array([p.y_m for p in points])
        if px.size == 0:
            return np.ones(0, dtype=bool)
        reach = math.ceil(radius_m / self.cell_m) + 1
        row, col, _ = self.index(px, py)
        rows = slice(max(0, int(row.min()) - reach), max(0, int(row.max()) + reach + 1))
        cols = slice(max(0, int(col.min()) - reach), max(0, int(col.max()) + reach + 1))
        hit_r, hit_c = np.nonzero(self.occupied((rows, cols)))
        if hit_r.size == 0:
            return np.ones(px.size, dtype=bool)
        x = self.x0_m + (hit_c + cols.start + 0.5) * self.cell_m
        y = self.y0_m + (hit_r + rows.start + 0.5) * self.cell_m
        near = np.hypot(x[None, :] - px[:, None], y[None, :] - py[:, None]) - self.cell_m / 2
        clear: BoolArray = (near >= radius_m).all(axis=1)
        return clear

    def _furthest_in_sight(
        self,
        a: Vec2,
        points: Sequence[Vec2],
        blocked: npt.NDArray[np.bool_],
        offset: tuple[int, int],
    ) -> Vec2:
        """The last of `points` in sight from `a` (`_in_sight`), the first if none is;
        looked for from the end, `SIGHT_BATCH` at a time.
        """
        for end in range(len(points), 0, -SIGHT_BATCH):
            batch = points[max(0, end - SIGHT_BATCH) : end]
            seen = np.flatnonzero(self._in_sight(a, batch, blocked, offset))
            if seen.size:
                return batch[int(seen[-1])]
        return points[0]

    def _in_sight(
        self,
        a: Vec2,
        ends: Sequence[Vec2],
        blocked: npt.NDArray[np.bool_],
        offset: tuple[int, int],
    ) -> npt.NDArray[np.bool_]:
        """Whether each segment from `a` to one of `ends` crosses only free cells of
        `blocked` (a window at `offset`), sampled every half cell.
        """
        across = [(b.x_m - a.x_m, b.y_m - a.y_m) for b in ends]
        samples = [max(2, math.ceil(math.hypot(*d) / (self.cell_m / 2))) for d in across]
        f = np.concatenate([_fractions(n) for n in samples])
        dx, dy = np.repeat(np.array(across), samples, axis=0).T
        row, col, _ = self.index(a.x_m + f * dx, a.y_m + f * dy)
        row, col = row - offset[0], col - offset[1]
        h, w = blocked.shape
        inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
        clear = inside & ~blocked[np.where(inside, row, 0), np.where(inside, col, 0)]
        starts = np.cumsum([0, *samples[:-1]])
        sight: npt.NDArray[np.bool_] = np.logical_and.reduceat(clear, starts)
        return sight

    def _window(self, a: Vec2, b: Vec2) -> Window:
        xs, ys = (a.x_m, b.x_m), (a.y_m, b.y_m)
        row, col, _ = self.index(
            np.array([min(xs) - PLAN_MARGIN_M, max(xs) + PLAN_MARGIN_M]),
            np.array([min(ys) - PLAN_MARGIN_M, max(ys) + PLAN_MARGIN_M]),
        )
        n = self.cells  # (clamped in Python: np.clip costs more than the rest)
        rows = slice(min(max(int(row[0]), 0), n), min(max(int(row[1]) + 1, 0), n))
        cols = slice(min(max(int(col[0]), 0), n), min(max(int(col[1]) + 1, 0), n))
        return rows, cols

    def _cell(self, p: Vec2, window: Window) -> Cell:
        row, col, _ = self.index(np.array([p.x_m]), np.array([p.y_m]))
        return int(row[0]) - window[0].start, int(col[0]) - window[1].start


def _sonar_rays(
    poses: Sequence[Pose2D], sonar: SonarGeometry
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Where each transducer is at each of `poses` (a row each; world frame, m) and which
    way it looks (rad).
    """
    rows = [
        (p.x_m, p.y_m, p.theta_rad, math.cos(p.theta_rad), math.sin(p.theta_rad)) for p in poses
    ]
    x, y, theta, c, s = np.array(rows)[:, :, None].transpose(1, 0, 2)
    ox = x + c * sonar.unit_x_m - s * sonar.unit_y_m
    oy = y + s * sonar.unit_x_m + c * sonar.unit_y_m
    return ox, oy, theta + sonar.unit_heading_rad


def _arc_points(
    sonar: SonarGeometry, rays: tuple[FloatArray, ...], r: FloatArray, near: BoolArray
) -> tuple[FloatArray, FloatArray]:
    """Where the `near` echoes mark their beams' right edge, centre and left edge (in that
    order per reading, the readings rows of `r` and of the `rays` (x, y, heading)).
    """
    if not near.any():
        return np.empty(0), np.empty(0)
    ox, oy, heading = rays
    angle = _arc_angles(sonar, heading, r)
    ox, oy = ox[:, None, :], oy[:, None, :]
    arcs = np.broadcast_to(near[:, None, :], angle.shape)
    x = (ox + r[:, None, :] * np.cos(angle))[arcs]
    y = (oy + r[:, None, :] * np.sin(angle))[arcs]
    return x, y


def _arc_angles(sonar: SonarGeometry, heading: FloatArray, r: FloatArray) -> FloatArray:
    """Which way each echo's arc points lie from their transducer (readings x places x
    transducers; the places `_ARC`'s): its heading, and a half beam either side, narrowed
    far off to `ARC_SPREAD_M` across.
    """
    half = np.minimum(sonar.half_beam_rad, np.arctan2(ARC_SPREAD_M, np.maximum(r, 1e-6)))
    angle: FloatArray = heading[:, None, :] + _ARC_OFFSETS * half[:, None, :]
    return angle


def _on_grid(cells: npt.NDArray[np.intp]) -> npt.NDArray[np.intp]:
    """The flat cell indices (`OccupancyMap._cells`) on the grid."""
    return cells[cells >= 0]


def _as_they_are(cells: npt.NDArray[np.intp]) -> npt.NDArray[np.intp]:
    """Flat cell indices known to be all on the grid."""
    return cells


def _rows(arrays: Sequence[npt.NDArray[Any]]) -> npt.NDArray[Any]:
    """The arrays (of one length) as the rows of one (a view of the only one)."""
    return arrays[0][None] if len(arrays) == 1 else np.array(arrays)


@functools.lru_cache(maxsize=16)
def _added(amount: int) -> npt.NDArray[np.int8]:
    """Evidence after adding `amount`, clipped to 0 to `MAX_EVIDENCE`, for every value
    (indexed by its byte: shared, never written).
    """
    before = np.arange(256, dtype=np.uint8).view(np.int8).astype(np.int16)
    after = np.clip(before + amount, 0, MAX_EVIDENCE).astype(np.int8)
    after.flags.writeable = False
    return after


# What a free sighting, then each of an arc's places, make of every evidence value (the
# compiled update's tables, in the order it marks).
_TABLES = np.stack([_added(-1), *(_added(amount) for _, amount in _ARC)])


@functools.lru_cache(maxsize=512)
def _fractions(samples: int) -> FloatArray:
    """`samples` fractions from 0 to 1 evenly (shared: never written)."""
    f = np.linspace(0.0, 1.0, samples)
    f.flags.writeable = False
    return f


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
    """Obstacles grown by `cells` (a disc): each row of the disc, `dy` off its centre,
    reaches `isqrt(cells^2 - dy^2)` cells either side; the obstacles grown that far
    along their rows, moved by `dy`.
    """
    along = [occupied]  # along[k]: grown k cells either side along the rows
    for dx in range(1, cells + 1):
        wider = along[-1].copy()
        wider[:, dx:] |= occupied[:, :-dx]
        wider[:, :-dx] |= occupied[:, dx:]
        along.append(wider)
    grown = along[cells].copy()
    for dy in range(1, cells + 1):
        row = along[math.isqrt(cells * cells - dy * dy)]
        grown[dy:] |= row[:-dy]
        grown[:-dy] |= row[dy:]
    return grown


def _wavefront(
    blocked: npt.NDArray[np.bool_],
    cost: FloatArray,
    row: int,
    col: int,
    *,
    start: tuple[int, int] | None = None,
) -> FloatArray:
    """Cost to reach (row, col) from every free cell: 8-connected moves, each costing its
    length (in cells) times the cost of the cell moved into; UNREACHABLE where no way is.

    Dijkstra's order a bucket at a time: the cells within the cheapest move of the least
    cost not final yet are final together (no way through another comes in under them),
    and a bucket is one numpy pass over the cells next to it (or the compiled loop's, the
    same bucket by bucket, where numba is). With `start`, it stops once
    `start`'s cost is final: every cell no costlier is final then, and every other is
    left above it (all `_downhill` from `start` reads). The costs are `_relaxed`'s, float
    for float: each is the least over the ways of the same sums in the same order.
    """
    cheapest = float(cost[~blocked].min(initial=np.inf))  # (the straight move's)
    if not 0.0 < cheapest < math.inf:
        return _relaxed(blocked, cost, row, col)
    h, w = blocked.shape
    wide, size = w + 2, (h + 2) * (w + 2)  # a border of closed cells: no bounds to check
    into = np.full((2, h + 2, w + 2), np.inf)  # a move's cost into a cell: straight, diagonal
    free = ~blocked
    into[0, 1:-1, 1:-1][free] = (_STRAIGHT * cost)[free]
    into[1, 1:-1, 1:-1][free] = (_DIAGONAL * cost)[free]
    moves = np.array([dy * wide + dx for dy, dx, _ in _MOVES])
    into_moves = moves + size * np.array([dy * dx != 0 for dy, dx, _ in _MOVES])
    goal = (row + 1) * wide + col + 1
    until = -1 if start is None else (start[0] + 1) * wide + start[1] + 1
    compiled = kernels(KERNELS)
    costs: FloatArray
    if compiled is not None:
        costs = compiled.wavefront(
            into.reshape(-1), (moves, into_moves), (size, goal, until), cheapest, UNREACHABLE
        )
    else:
        costs = _buckets(into.reshape(-1), (moves, into_moves), (size, goal, until), cheapest)
    dist = costs.reshape(h + 2, w + 2)[1:-1, 1:-1]
    ends = dist[start] if start is not None else dist
    furthest = float(np.max(ends, where=ends < UNREACHABLE, initial=0.0))
    if furthest >= (_sweeps(blocked) - 1) * cheapest:
        return _relaxed(blocked, cost, row, col)  # a way too long for its sweeps to reach
    return dist


def _buckets(
    into_flat: FloatArray,
    steps: tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]],
    cells: tuple[int, int, int],
    cheapest: float,
) -> FloatArray:
    """`_wavefront`'s costs over the bordered grid, flat: its buckets, each one numpy pass
    (`grid_kernels.wavefront` says what the arguments are).
    """
    (moves, into_moves), (size, goal, until) = steps, cells
    costs = np.full(size, UNREACHABLE)
    pending = np.full(size, np.inf)  # the cost of a cell reached, not final yet
    costs[goal] = pending[goal] = 0.0
    while (least := float(np.minimum.reduce(pending))) < math.inf:
        bound = least + cheapest
        if until >= 0 and costs[until] < bound:
            break
        bucket = (pending < bound).nonzero()[0]
        pending[bucket] = np.inf
        offered = costs[bucket][:, None] + into_flat[bucket[:, None] + into_moves]
        reached = bucket[:, None] + moves
        better = offered < costs[reached]
        reached, offered = reached[better], offered[better]
        np.minimum.at(costs, reached, offered)
        pending[reached] = costs[reached]
    return costs


def _sweeps(blocked: npt.NDArray[np.bool_]) -> int:
    """How many sweeps `_relaxed` makes at most."""
    return 8 * sum(blocked.shape)


def _relaxed(blocked: npt.NDArray[np.bool_], cost: FloatArray, row: int, col: int) -> FloatArray:
    """`_wavefront` by relaxing every cell at once until nothing changes (or `_sweeps`
    times: a cell more moves than that from (row, col) keeps the best it had by then).
    """
    dist = np.full(blocked.shape, UNREACHABLE)
    dist[row, col] = 0.0
    for _ in range(_sweeps(blocked)):
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
