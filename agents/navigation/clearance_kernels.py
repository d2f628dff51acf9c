"""`corridor_clearance`'s pass as one compiled loop (numba; `phalanx.core.compiled`).

The arithmetic is the numpy pass's, operation for operation: the same components of the
same offsets, the same squares, square roots and floors, the least taken per heading.
Importing this module imports numba.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from phalanx.agents.perception import FloatArray


@numba.njit(cache=True, nogil=True)
def corridor(
    x: FloatArray,
    y: FloatArray,
    c: FloatArray,
    s: FloatArray,
    ox: FloatArray,
    oy: FloatArray,
    w2: float,
    turning: bool,
) -> FloatArray:
    """Per heading (cosine `c`, sine `s`), the first touch of any disc of squared radius
    `w2` at (`ox`, `oy`) moving along it (turned to face it if `turning`, else sliding
    as it stands) with a point (`x`, `y`); inf where none touches.
    """
    out = np.empty(c.size)
    for h in range(c.size):
        ch, sh = c[h], s[h]
        best = math.inf
        for j in range(ox.size):
            sx, sy = ox[j], oy[j]
            own = turning and sx == 0.0 and sy == 0.0  # (the points' components as they are)
            if turning:
                sx, sy = ch * sx - sh * sy, sh * sx + ch * sy  # the slot turned with the heading
            for p in range(x.size):
                dx, dy = (x[p], y[p]) if own else (x[p] - sx, y[p] - sy)
                lat = dy * ch - dx * sh
                lat2 = lat * lat
                if lat2 < w2:
                    f = dx * ch + dy * sh
                    if f > 0.0:
                        touch = f - math.sqrt(max(w2 - lat2, 0.0))
                        best = min(best, max(touch, 0.0))
        out[h] = best
    return out
