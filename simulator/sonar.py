"""Sonar ray casting: each transducer casts a fan of rays across its beam width and
reads the nearest hit among circles (obstacles and other robots) and polygon edges.

`cast_rings` casts every robot's ring in one vectorised pass: the rays of all robots
against the discs near each (pairs found by the world's broad phase), then the nearest
hit of each transducer's fan. Each (ray, disc) distance is worked out with the same
floating-point operations as `ray_circle_hits` does for one robot, and a minimum does
not depend on the order it is taken in, so the ranges are bit-identical either way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import numpy.typing as npt

from phalanx.core.robot_params import SonarParams

FloatArray = npt.NDArray[np.float64]
# How much wider than the exact cone a disc's candidate rays are taken (rad, m).
_CONE_MARGIN_RAD = 1e-3
_CONE_MARGIN_M = 1e-6


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

    @cached_property
    def mount_m(self) -> float:
        """The furthest ray origin from the body origin (m)."""
        return float(np.hypot(self.origin_x, self.origin_y).max(initial=0.0))

    @cached_property
    def sorted_angles(self) -> tuple[npt.NDArray[np.intp], FloatArray]:
        """The rays in order of their body-frame angle in [-pi, pi): (ray, angle)."""
        wrapped = np.mod(self.angle_rad + math.pi, 2.0 * math.pi) - math.pi
        order = np.argsort(wrapped, kind="stable")
        return order, wrapped[order]

    @cached_property
    def extended_angles(self) -> FloatArray:
        """`sorted_angles`' angles, then again a turn below and a turn above."""
        ordered = self.sorted_angles[1]
        return np.concatenate([ordered - 2.0 * math.pi, ordered, ordered + 2.0 * math.pi])

    @cached_property
    def fans_in_order(self) -> bool:
        """Whether the rays are every transducer's fan in turn, all fans alike."""
        fan = self.angle_rad.size // self.units
        return fan * self.units == self.angle_rad.size and np.array_equal(
            self.unit_of_ray, np.repeat(np.arange(self.units), fan)
        )

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
    t = circle_hits_at(
        ox[:, None], oy[:, None], dx[:, None], dy[:, None], cx[None, :], cy[None, :], r[None, :]
    )  # every ray against every circle
    return np.asarray(np.min(t, axis=1), dtype=np.float64)


def nearest_segment_hits(
    ox: FloatArray,
    oy: FloatArray,
    dx: FloatArray,
    dy: FloatArray,
    ax: FloatArray,
    ay: FloatArray,
    ex: FloatArray,
    ey: FloatArray,
) -> FloatArray:
    """Distance along each ray to the nearest segment (from a, extent (ex, ey) = b - a),
    inf if none; a ray parallel to a segment meets it nowhere (its t and s are NaN,
    which meet no bound).
    """
    ex, ey = ex[None, :], ey[None, :]
    wx, wy = ax[None, :] - ox[:, None], ay[None, :] - oy[:, None]
    dx, dy = dx[:, None], dy[:, None]
    denom = dx * ey - dy * ex
    safe = np.where(np.abs(denom) < 1e-12, np.nan, denom)
    t = (wx * ey - wy * ex) / safe
    s = (wx * dy - wy * dx) / safe
    hit = (t >= 0.0) & (s >= 0.0) & (s <= 1.0)
    return np.asarray(np.min(np.where(hit, t, np.inf), axis=1), dtype=np.float64)


def ring_rays(
    ring: SonarRing, x: FloatArray, y: FloatArray, th: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """World-frame origins and unit directions of every robot's rays, (robots, rays)."""
    c, s = np.cos(th)[:, None], np.sin(th)[:, None]
    ox = x[:, None] + c * ring.origin_x - s * ring.origin_y
    oy = y[:, None] + s * ring.origin_x + c * ring.origin_y
    ang = th[:, None] + ring.angle_rad
    return ox, oy, np.cos(ang), np.sin(ang)


def circle_hits_at(
    ox: FloatArray,
    oy: FloatArray,
    dx: FloatArray,
    dy: FloatArray,
    cx: FloatArray,
    cy: FloatArray,
    r: FloatArray,
) -> FloatArray:
    """Distance along ray e (origin, unit direction) to circle e, inf if it misses,
    element by element (arrays that broadcast together: `ray_circle_hits` gives it every
    ray against every circle).
    """
    fx, fy = ox - cx, oy - cy
    b = fx * dx + fy * dy
    c = fx * fx + fy * fy - r**2
    disc = b * b - c
    root = np.sqrt(np.maximum(disc, 0.0))
    back = -b
    t_near, t_far = back - root, back + root
    t = np.where(t_near >= 0.0, t_near, np.where(t_far >= 0.0, 0.0, np.inf))
    return np.asarray(np.where(disc >= 0.0, t, np.inf), dtype=np.float64)


def rays_towards(
    ring: SonarRing, rel_bearing: FloatArray, distance: FloatArray, radius: FloatArray
) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """(pair, ray) of every ray of a robot's ring that may meet disc `pair`: the disc's
    centre at `distance` and bearing `rel_bearing` (body frame, from the body origin).

    A ray leaves from within `mount_m` of the body origin, so it can only meet the disc
    if it points within asin(mount / d) + asin(radius / (d - mount)) of the bearing; a
    disc that may hold a ray's origin takes every ray. The cone is widened a little so
    rounding never leaves out a ray that hits: the rays left out would all miss.
    """
    rays = ring.angle_rad.size
    order = ring.sorted_angles[0]
    m = ring.mount_m
    inside = distance - m <= radius + _CONE_MARGIN_M
    safe = np.where(inside, 1.0, distance)
    half = (
        np.arcsin(np.minimum(1.0, m / safe))
        + np.arcsin(np.minimum(1.0, radius / np.maximum(safe - m, 1e-9)))
        + _CONE_MARGIN_RAD
    )
    extended = ring.extended_angles
    rel = np.mod(rel_bearing + math.pi, 2.0 * math.pi) - math.pi
    whole = inside | (half >= math.pi)
    lo = np.where(whole, rays, np.searchsorted(extended, rel - half, "left"))
    hi = np.where(whole, 2 * rays, np.searchsorted(extended, rel + half, "right"))
    counts = hi - lo
    pair = np.repeat(np.arange(rel.size), counts)
    within = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
    return pair, order[(np.repeat(lo, counts) + within) % rays]


def per_unit(ring: SonarRing, hits: FloatArray) -> FloatArray:
    """(robots, rays) -> (robots, transducers): the nearest hit of each fan."""
    fan = hits.shape[1] // ring.units
    if ring.fans_in_order:
        return np.asarray(hits.reshape(hits.shape[0], ring.units, fan).min(axis=2))
    out = np.full((hits.shape[0], ring.units), np.inf)
    for k in range(ring.units):
        out[:, k] = hits[:, ring.unit_of_ray == k].min(axis=1, initial=np.inf)
    return out
