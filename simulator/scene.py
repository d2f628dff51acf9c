"""What the robots' sonar rings hear in a world: its obstacle circles and wall edges, and
the other robots' discs. `SonarScene.cast` casts any robots' rings against it in one
vectorised pass, against only the discs within reach of each (found through a uniform
grid once the fleet is large: `close_pairs`).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from phalanx.simulator.contacts import Edges
from phalanx.simulator.pairs import close_pairs
from phalanx.simulator.sonar import (
    SonarRing,
    circle_hits_at,
    per_unit,
    ray_segment_hits,
    rays_towards,
    ring_rays,
)

FloatArray = npt.NDArray[np.float64]
IndexArray = npt.NDArray[np.intp]

# A disc further than this beyond the sonar's reach is left out of the cast: its echo
# could only come back shorter than max range through noise of over 1 m (50 sigma and more).
_CAST_MARGIN_M = 1.0
_CAST_MARGIN_SIGMAS = 50.0
# Rays x discs (or edges) worked out at once, to bound memory on large fleets.
_CHUNK = 1 << 18


class SonarScene:
    """A world's obstacles as its robots' sonar hears them, with the sonar's noise
    (`rng`: the world's own random stream, drawn in robot order).
    """

    def __init__(
        self,
        ring: SonarRing,
        circles: FloatArray,
        edges: Edges,
        *,
        robot_radius_m: float,
        sonar_std_m: float,
        rng: np.random.Generator,
    ) -> None:
        self.ring, self.circles, self.edges = ring, circles, edges
        self.radius_m, self.sonar_std_m, self.rng = robot_radius_m, sonar_std_m, rng

    def cast(self, x: FloatArray, y: FloatArray, th: FloatArray, idx: IndexArray) -> FloatArray:
        """Sonar ranges (len(idx), transducers) of robots `idx` of those at `x`, `y`,
        `th` (every robot of the world), noise drawn in their order.
        """
        ring = self.ring
        rays = ring_rays(ring, x[idx], y[idx], th[idx])
        owner, cx, cy, r = self._nearby_discs(x, y, idx)
        # Only the rays that point towards a disc are tested against it.
        ox_, oy_, oth = x[idx][owner], y[idx][owner], th[idx][owner]
        bearing = np.arctan2(cy - oy_, cx - ox_) - oth
        pair, ray = rays_towards(ring, bearing, np.hypot(cx - ox_, cy - oy_), r)
        flat = owner[pair] * ring.angle_rad.size + ray
        ox, oy, dx, dy = (a.ravel()[flat] for a in rays)
        nearest = np.full(rays[0].size, np.inf)
        np.minimum.at(nearest, flat, circle_hits_at(ox, oy, dx, dy, cx[pair], cy[pair], r[pair]))
        hits = nearest.reshape(rays[0].shape)
        if self.edges.ax.size:
            hits = np.minimum(hits, self._edge_hits(rays))
        ranges = per_unit(ring, hits)
        if self.sonar_std_m > 0.0:
            ranges = ranges + self.rng.normal(0.0, self.sonar_std_m, ranges.shape)
        return np.asarray(np.clip(ranges, ring.min_range_m, ring.max_range_m), dtype=np.float64)

    def _edge_hits(self, rays: tuple[FloatArray, ...]) -> FloatArray:
        e = self.edges
        ox, oy, dx, dy = (a.ravel() for a in rays)
        out = np.empty(ox.size)
        step = max(1, _CHUNK // e.ax.size)
        for lo in range(0, ox.size, step):
            part = slice(lo, lo + step)
            out[part] = ray_segment_hits(
                ox[part], oy[part], dx[part], dy[part], e.ax, e.ay, e.bx, e.by
            )
        return out.reshape(rays[0].shape)

    def _nearby_discs(
        self, x_all: FloatArray, y_all: FloatArray, idx: IndexArray
    ) -> tuple[IndexArray, FloatArray, FloatArray, FloatArray]:
        """(row of idx, centre x, y, radius) of every disc the sonar of robots `idx` may
        hear: the obstacle circles within reach, and every other robot
        whose centre is within `reach` (the same test, pair by pair, as always).
        """
        radius = self.radius_m
        reach = self.ring.max_range_m + radius + 0.5
        x, y = x_all[idx], y_all[idx]
        rows, cx, cy, r = [], [], [], []
        if len(self.circles):
            circles = self.circles
            horizon = (
                self.ring.max_range_m
                + self.ring.mount_m
                + _CAST_MARGIN_M
                + _CAST_MARGIN_SIGMAS * self.sonar_std_m
            )
            d = np.hypot(x[:, None] - circles[:, 0], y[:, None] - circles[:, 1])
            ri, k = np.nonzero(d - circles[:, 2] < horizon)
            rows.append(ri)
            cx.append(circles[k, 0])
            cy.append(circles[k, 1])
            r.append(circles[k, 2])
        if idx.size == x_all.size:
            ri, j = close_pairs(x_all, y_all, reach)
        else:
            ri, j = np.nonzero(np.ones((idx.size, x_all.size), dtype=bool))
            ri, j = ri[j != idx[ri]], j[j != idx[ri]]
        near = np.hypot(x_all[j] - x[ri], y_all[j] - y[ri]) < reach
        rows.append(ri[near])
        cx.append(x_all[j[near]])
        cy.append(y_all[j[near]])
        r.append(np.full(int(near.sum()), radius))
        cat = np.concatenate
        return cat(rows), cat(cx), cat(cy), cat(r)
