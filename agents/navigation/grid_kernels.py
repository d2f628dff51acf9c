"""`OccupancyMap`'s update and its route's wavefront as compiled loops (numba;
`phalanx.core.compiled`).

The update's arithmetic is the numpy update's, operation for operation: the same points
along each ray and on each echo's arc (from the cosines and sines numpy worked out), the
same cells, each marking's cells changed once whatever how often they are listed (the
numpy update reads them all before it writes any), the markings in the same order. The
wavefront takes numpy's buckets in the same order with the same sums.
Importing this module imports numba.
"""

from __future__ import annotations

import heapq

import numba
import numpy as np
import numpy.typing as npt

from phalanx.agents.perception import BoolArray, FloatArray

Int8Array = npt.NDArray[np.int8]
Int64Array = npt.NDArray[np.int64]


@numba.njit(cache=True, nogil=True)
def add_readings(
    evidence: Int8Array,
    seen: BoolArray,
    stamp: Int64Array,
    mark: int,
    tables: Int8Array,
    grid: tuple[float, float, float, int],
    rays: tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray],
    steps: FloatArray,
    arcs: tuple[FloatArray, BoolArray, FloatArray, FloatArray],
) -> int:
    """Each reading (a row) in turn: every point along its rays short of their reach
    freed (`tables[0]`), then each of its echoes' arc points (`tables[1 + k]` for the
    k-th of the arc's places, edge, axis, edge) marked; every cell touched seen.

    `evidence`, `seen`, `stamp`: the grid's cells, flat (`stamp`: the marking that last
    changed each, written here; the markings are numbered on from `mark`, and the last
    number is returned); `grid`: the grid's corner x and y, its cell's size, its
    cells a side; `rays`: each transducer's place x, y, the cosine and sine of its
    heading and its free reach (readings x transducers); `steps`: the distances along a
    ray; `arcs`: the ranges, which echoes mark the map, and the cosine and sine of each
    arc point's direction (readings x places x transducers).
    """
    ox, oy, ch, sh, reach = rays
    r, near, ca, sa = arcs
    for i in range(ox.shape[0]):
        mark += 1
        for u in range(ox.shape[1]):
            for along in steps:
                if along < reach[i, u]:
                    x = ox[i, u] + along * ch[i, u]
                    y = oy[i, u] + along * sh[i, u]
                    _mark(evidence, seen, stamp, tables[0], mark, grid, (x, y))
        if not near[i].any():
            continue
        for k in range(ca.shape[1]):
            mark += 1
            for u in range(ox.shape[1]):
                if near[i, u]:
                    x = ox[i, u] + r[i, u] * ca[i, k, u]
                    y = oy[i, u] + r[i, u] * sa[i, k, u]
                    _mark(evidence, seen, stamp, tables[1 + k], mark, grid, (x, y))
    return mark


@numba.njit(inline="always")
def _mark(
    evidence: Int8Array,
    seen: BoolArray,
    stamp: Int64Array,
    table: Int8Array,
    mark: int,
    grid: tuple[float, float, float, int],
    point: tuple[float, float],
) -> None:
    """The cell `point` lies in changed by `table` (indexed by its evidence's byte), once
    in marking `mark`, and seen; nothing off the grid.
    """
    x0, y0, cell, n = grid
    col = np.floor((point[0] - x0) / cell)
    row = np.floor((point[1] - y0) / cell)
    if not (0.0 <= col < n and 0.0 <= row < n):
        return
    at = int(row) * n + int(col)
    seen[at] = True
    if stamp[at] != mark:
        stamp[at] = mark
        evidence[at] = table[evidence[at] & 0xFF]


@numba.njit(cache=True, nogil=True)
def wavefront(
    into: FloatArray,
    moves: tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]],
    cells: tuple[int, int, int],
    cheapest: float,
    unreachable: float,
) -> FloatArray:
    """`grid._wavefront`'s buckets, each the same as numpy's: every pending cell below
    the least pending cost plus `cheapest` made final together, every move out of them
    offered at the cost before any of the bucket's offers is taken, then the least offer
    taken per cell and the cells bettered pending at it; stopping where numpy stops, so
    the cells not final hold what numpy's pass leaves in them too.

    `into`: a move's cost into each cell (straight moves' cells, then diagonal ones',
    flat, bordered by closed cells); `moves`: each move's step between flat cells, and
    its step into `into`; `cells`: how many a bordered grid holds, the goal's, and the
    cell to stop at once final (-1: none).
    """
    size, goal, until = cells
    step, into_step = moves
    costs = np.full(size, unreachable)
    pending = np.full(size, np.inf)
    costs[goal] = pending[goal] = 0.0
    heap = [(0.0, goal)]  # (pending cost, cell); an entry whose cell moved on is stale
    bucket = np.empty(size, dtype=np.intp)
    offers = np.empty(8 * size)
    reached = np.empty(8 * size, dtype=np.intp)
    while True:
        while heap and pending[heap[0][1]] != heap[0][0]:
            heapq.heappop(heap)
        if not heap:
            break
        bound = heap[0][0] + cheapest
        if until >= 0 and costs[until] < bound:
            break
        count = 0
        while heap and heap[0][0] < bound:
            cost, cell = heapq.heappop(heap)
            if pending[cell] == cost:
                pending[cell] = np.inf
                bucket[count] = cell
                count += 1
        made = 0
        for b in range(count):
            cell = bucket[b]
            for k in range(step.size):
                offer = costs[cell] + into[cell + into_step[k]]
                if offer < costs[cell + step[k]]:
                    offers[made] = offer
                    reached[made] = cell + step[k]
                    made += 1
        for m in range(made):
            costs[reached[m]] = min(costs[reached[m]], offers[m])
        for m in range(made):
            cell = reached[m]
            if pending[cell] != costs[cell]:
                pending[cell] = costs[cell]
                heapq.heappush(heap, (costs[cell], cell))
    return costs
