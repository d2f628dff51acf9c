"""The plain ray-segment test the simulator's lean one (`nearest_segment_hits`) is
held to: the same arithmetic with a parallel pair masked out, segment by end points.
Shared by the simulator's tests.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def ray_segment_hits(
    ox: FloatArray,
    oy: FloatArray,
    dx: FloatArray,
    dy: FloatArray,
    ax: FloatArray,
    ay: FloatArray,
    bx: FloatArray,
    by: FloatArray,
) -> FloatArray:
    """Distance along each ray to the nearest segment (a -> b), inf if none."""
    if ax.size == 0:
        return np.full(ox.shape, np.inf)
    ex, ey = (bx - ax)[None, :], (by - ay)[None, :]
    wx, wy = ax[None, :] - ox[:, None], ay[None, :] - oy[:, None]
    denom = dx[:, None] * ey - dy[:, None] * ex
    parallel = np.abs(denom) < 1e-12
    safe = np.where(parallel, 1.0, denom)
    t = (wx * ey - wy * ex) / safe
    s = (wx * dy[:, None] - wy * dx[:, None]) / safe
    hit = (~parallel) & (t >= 0.0) & (s >= 0.0) & (s <= 1.0)
    return np.asarray(np.min(np.where(hit, t, np.inf), axis=1), dtype=np.float64)
