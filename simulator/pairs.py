"""Which points are near which: pair by pair for a small fleet (a dense matrix), through a
uniform grid for a large one. The world's contact checks and its sonar cast share these.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

# Up to this many robots, distances are checked pair by pair (a dense matrix); beyond,
# through a uniform grid.
_PAIRWISE_MAX = 64
# Up to this many points, `any_pair_within` checks them in plain floats.
_FEW = 8


def grid_pairs(
    ax: FloatArray, ay: FloatArray, bx: FloatArray, by: FloatArray, cell_m: float
) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """(i, j) of every point a_i and b_j in the same or neighbouring cells of a grid of
    `cell_m`: a superset of the pairs closer than `cell_m`, sorted by i.
    """
    kax, kay = np.floor(ax / cell_m).astype(np.int64), np.floor(ay / cell_m).astype(np.int64)
    kbx, kby = np.floor(bx / cell_m).astype(np.int64), np.floor(by / cell_m).astype(np.int64)
    x0 = min(int(kax.min()), int(kbx.min())) - 1
    y0 = min(int(kay.min()), int(kby.min())) - 1
    width = max(int(kay.max()), int(kby.max())) - y0 + 2
    keys = (kbx - x0) * width + (kby - y0)
    order = np.argsort(keys, kind="stable")
    ordered = keys[order]
    firsts, lasts = [], []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            q = (kax + dx - x0) * width + (kay + dy - y0)
            firsts.append(np.searchsorted(ordered, q, "left"))
            lasts.append(np.searchsorted(ordered, q, "right"))
    lo, hi = np.stack(firsts, axis=1).ravel(), np.stack(lasts, axis=1).ravel()
    counts = hi - lo
    total = int(counts.sum())
    i = np.repeat(np.repeat(np.arange(ax.size), 9), counts)
    start = np.repeat(lo - (np.cumsum(counts) - counts), counts)
    return i, order[start + np.arange(total)]


def close_pairs(
    x: FloatArray, y: FloatArray, distance_m: float
) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """(i, j), i != j, of every two robots whose centres may lie within `distance_m`
    (every pair of a small fleet; grid neighbours of a large one), sorted by i.
    """
    n = x.size
    if n <= _PAIRWISE_MAX:
        i, j = np.nonzero(~np.eye(n, dtype=bool))
        return i, j
    i, j = grid_pairs(x, y, x, y, distance_m)
    keep = i != j
    return i[keep], j[keep]


def any_pair_within(x: FloatArray, y: FloatArray, distance_m: float) -> bool:
    """Whether any two of the points (x, y) lie closer than `distance_m`."""
    if len(x) < 2:
        return False
    # a hair wide of the grid's exact hypot test: never misses a contact it would find
    limit = (distance_m * (1.0 + 1e-9)) ** 2
    if len(x) <= _FEW:  # (the same arithmetic in plain floats: cheaper than numpy's calls)
        xs, ys = x.tolist(), y.tolist()
        for k, (xi, yi) in enumerate(zip(xs, ys, strict=True)):
            for xj, yj in zip(xs[k + 1 :], ys[k + 1 :], strict=True):
                dx, dy = xi - xj, yi - yj  # (numpy's ** 2 is dx * dx, not pow)
                if dx * dx + dy * dy < limit:
                    return True
        return False
    if len(x) <= _PAIRWISE_MAX:
        d2 = (x[:, None] - x[None, :]) ** 2 + (y[:, None] - y[None, :]) ** 2
        np.fill_diagonal(d2, np.inf)
        return bool(d2.min() < limit)
    i, j = close_pairs(x, y, 2.0 * distance_m)
    return bool(np.any((x[i] - x[j]) ** 2 + (y[i] - y[j]) ** 2 < limit))
