"""`SonarGeometry.arcs_met`'s test as one compiled loop (numba; `phalanx.core.compiled`).

The arithmetic is the numpy test's, operation for operation: each echo's point nearest
a disc from the direction numpy worked out, its squared distance from the disc's centre
against the squared radius a hair either side, and `hypot` (the C library's, as numpy's)
only where that leaves the answer in doubt. Importing this module imports numba.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

from phalanx.agents.perception import BoolArray, FloatArray


@numba.njit(cache=True, nogil=True)
def arcs_met(
    units: tuple[FloatArray, FloatArray],
    r: FloatArray,
    discs: tuple[npt.NDArray[np.intp], FloatArray, FloatArray, FloatArray, FloatArray],
    radius: tuple[float, float, float],
    met: BoolArray,
) -> None:
    """Mark in `met` (readings x transducers) each transducer whose echo arc at its range
    `r` (the same shape) passes within a disc its reading owns.

    `units`: the transducers' places x, y; `discs`: each disc's owner (a row of `r`),
    centre x, y and, per transducer, the direction (cosine, sine) of the point of its
    beam nearest the centre; `radius`: the discs' radius, and its square a hair less and
    a hair more.
    """
    ux, uy = units
    owner, cx, cy, d0, d1 = discs
    radius_m, inside2, doubt2 = radius
    for k in range(owner.size):
        row = owner[k]
        for u in range(ux.size):
            if met[row, u]:
                continue
            dx = ux[u] + r[row, u] * d0[k, u] - cx[k]
            dy = uy[u] + r[row, u] * d1[k, u] - cy[k]
            d2 = dx * dx + dy * dy
            if d2 < inside2 or (d2 <= doubt2 and math.hypot(dx, dy) < radius_m):
                met[row, u] = True
