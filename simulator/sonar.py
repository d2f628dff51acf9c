"""Sonar ray casting: each transducer casts a fan of rays across its beam width and
reads the nearest hit among circles (obstacles and other robots) and polygon edges.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from phalanx.core.config import SonarParams

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class SonarRing:
    """Ray origins and directions of a sonar ring in the robot's body frame."""

    origin_x: FloatArray  # one entry per ray
    origin_y: FloatArray
    angle_rad: FloatArray
    unit_of_ray: npt.NDArray[np.intp]
    units: int
    max_range_m: float
    min_range_m: float

    @classmethod
    def from_params(cls, sonar: SonarParams) -> SonarRing:
        """Fan `rays_per_beam` rays evenly across each transducer's beam width."""
        n = sonar.rays_per_beam
        half = math.radians(sonar.beam_width_deg) / 2
        spread = np.linspace(-half, half, n) if n > 1 else np.zeros(1)
        ox, oy, ang, unit = [], [], [], []
        for i, u in enumerate(sonar.units):
            for offset in spread:
                ox.append(u.x_m)
                oy.append(u.y_m)
                ang.append(math.radians(u.heading_deg) + offset)
                unit.append(i)
        return cls(
            np.array(ox),
            np.array(oy),
            np.array(ang),
            np.array(unit, dtype=np.intp),
            len(sonar.units),
            sonar.max_range_m,
            sonar.min_range_m,
        )


def ray_circle_hits(
    ox: FloatArray,
    oy: FloatArray,
    dx: FloatArray,
    dy: FloatArray,
    cx: FloatArray,
    cy: FloatArray,
    r: FloatArray,
) -> FloatArray:
    """Distance along each ray (unit direction) to the nearest circle, inf if none."""
    if cx.size == 0:
        return np.full(ox.shape, np.inf)
    fx, fy = ox[:, None] - cx[None, :], oy[:, None] - cy[None, :]
    b = fx * dx[:, None] + fy * dy[:, None]
    c = fx * fx + fy * fy - r[None, :] ** 2
    disc = b * b - c
    root = np.sqrt(np.maximum(disc, 0.0))
    t_near, t_far = -b - root, -b + root
    t = np.where(t_near >= 0.0, t_near, np.where(t_far >= 0.0, 0.0, np.inf))
    t = np.where(disc >= 0.0, t, np.inf)
    return np.asarray(np.min(t, axis=1), dtype=np.float64)


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
