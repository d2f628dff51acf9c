"""What the robots' sonar rings hear in a world: its obstacle circles and wall edges, and
the other robots' discs. `SonarScene.cast` casts any robots' rings against it in one
vectorised pass, against only the discs and wall edges within reach of each (the other
robots found through a uniform grid once the fleet is large: `close_pairs`). A small
world's discs are tested against every ray of a robot in one block; a larger one's
against only the rays that point towards each (`rays_towards`): the same hits.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from phalanx.simulator.contacts import Edges
from phalanx.simulator.pairs import close_pairs
from phalanx.simulator.sonar import (
    SonarRing,
    circle_hits_at,
    nearest_segment_hits,
    per_unit,
    rays_towards,
    ring_rays,
)

FloatArray = npt.NDArray[np.float64]
IndexArray = npt.NDArray[np.intp]
BoolArray = npt.NDArray[np.bool_]
Rays = tuple[FloatArray, FloatArray, FloatArray, FloatArray]

# A disc or wall further than this beyond the sonar's reach is left out of the cast: its
# echo could only come back shorter than max range through noise of over 1 m (50 sigma
# and more). Without noise it could not at all, and the margin is only wider than rounding.
_CAST_MARGIN_M = 1.0
_CAST_MARGIN_SIGMAS = 50.0
_EXACT_MARGIN_M = 1e-6
# Rays x discs (or edges) worked out at once, to bound memory on large fleets.
_CHUNK = 1 << 18
# Up to this many ray x disc tests, a cast tests every ray of a robot against every disc
# it may hear (a block, few numpy calls); beyond, only the rays pointing towards each.
_DENSE_MAX = 1 << 13


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
        noise_m = _CAST_MARGIN_M + _CAST_MARGIN_SIGMAS * sonar_std_m
        # how far from a robot's centre a circle's or a wall's nearest point may be and
        # still be cast against (the furthest transducer's mount plus the sonar's reach)
        self.horizon_m = (
            ring.max_range_m + ring.mount_m + (noise_m if sonar_std_m > 0.0 else _EXACT_MARGIN_M)
        )
        self._circle_x, self._circle_y, self._circle_r = (circles[:, k].copy() for k in range(3))
        self._radii = np.zeros(0)  # (`_disc_radii`)
        # each edge's bounding box: lowest x, y, highest x, y
        self._edge_boxes = (
            np.minimum(edges.ax, edges.bx),
            np.minimum(edges.ay, edges.by),
            np.maximum(edges.ax, edges.bx),
            np.maximum(edges.ay, edges.by),
        )

    def cast(self, x: FloatArray, y: FloatArray, th: FloatArray, idx: IndexArray) -> FloatArray:
        """Sonar ranges (len(idx), transducers) of robots `idx` of those at `x`, `y`,
        `th` (every robot of the world), noise drawn in their order.
        """
        ring = self.ring
        at = x[idx], y[idx]
        rays = ring_rays(ring, *at, th[idx])
        if idx.size * (len(self.circles) + x.size) * ring.angle_rad.size <= _DENSE_MAX:
            hits = self._hits_every_ray(x, y, idx, at, rays)
        else:
            hits = self._hits_towards(x, y, th, idx, rays)
        walls = self._near_edges(*at)
        if walls.size:
            hits = np.minimum(hits, self._edge_hits(rays, walls))
        ranges = per_unit(ring, hits)
        if self.sonar_std_m > 0.0:
            ranges = ranges + self.rng.normal(0.0, self.sonar_std_m, ranges.shape)
        # (np.clip's arithmetic, max then min, without its call's overhead)
        clipped = np.minimum(np.maximum(ranges, ring.min_range_m), ring.max_range_m)
        return np.asarray(clipped, dtype=np.float64)

    def _hits_towards(
        self, x: FloatArray, y: FloatArray, th: FloatArray, idx: IndexArray, rays: Rays
    ) -> FloatArray:
        """Each ray's nearest disc hit (robots, rays), inf if none: every disc a robot
        may hear tested against only the rays that point towards it.
        """
        ring = self.ring
        owner, cx, cy, r = self._nearby_discs(x, y, idx)
        ox_, oy_, oth = x[idx][owner], y[idx][owner], th[idx][owner]
        bearing = np.arctan2(cy - oy_, cx - ox_) - oth
        pair, ray = rays_towards(ring, bearing, np.hypot(cx - ox_, cy - oy_), r)
        flat = owner[pair] * ring.angle_rad.size + ray
        ox, oy, dx, dy = (a.ravel()[flat] for a in rays)
        nearest = np.full(rays[0].size, np.inf)
        np.minimum.at(nearest, flat, circle_hits_at(ox, oy, dx, dy, cx[pair], cy[pair], r[pair]))
        return nearest.reshape(rays[0].shape)

    def _hits_every_ray(
        self,
        x_all: FloatArray,
        y_all: FloatArray,
        idx: IndexArray,
        at: tuple[FloatArray, FloatArray],
        rays: Rays,
    ) -> FloatArray:
        """`_hits_towards` with every ray tested against every disc its robot may hear
        (the same discs, `_heard`), in a block (robots, discs, rays): fewer numpy calls,
        for a small world. The rays the cone leaves out all miss, and a minimum does not
        depend on what misses, so each hit is the same (but for a zero's sign, when a ray
        starts on two discs' edges at once: the minimum range's clip takes it off).
        `at`: robots `idx`'s x and y.
        """
        heard = self._heard(x_all, y_all, idx, at)
        discs = np.flatnonzero(heard.any(axis=0))  # (only those some robot hears)
        cx = np.concatenate((self._circle_x, x_all))[discs, None]
        cy = np.concatenate((self._circle_y, y_all))[discs, None]
        r = self._disc_radii(x_all.size)[discs, None]
        ox, oy, dx, dy = (a[:, None, :] for a in rays)
        t = circle_hits_at(ox, oy, dx, dy, cx, cy, r)
        t = np.where(heard[:, discs, None], t, np.inf)
        return np.asarray(t.min(axis=1, initial=np.inf))

    def _disc_radii(self, robots: int) -> FloatArray:
        """The radii of the world's circles, then of `robots` robots."""
        if self._radii.size != self._circle_r.size + robots:
            self._radii = np.concatenate((self._circle_r, np.full(robots, self.radius_m)))
        return self._radii

    def _heard(
        self,
        x_all: FloatArray,
        y_all: FloatArray,
        idx: IndexArray,
        at: tuple[FloatArray, FloatArray],
    ) -> BoolArray:
        """(robot of idx, disc): whether `_nearby_discs` gives it the disc, the world's
        circles then every robot, by the same tests.
        """
        x, y = at[0][:, None], at[1][:, None]
        d = np.hypot(x - self._circle_x, y - self._circle_y)
        circles = d - self._circle_r < self.horizon_m
        reach = self.ring.max_range_m + self.radius_m + 0.5
        robots = np.hypot(x_all - x, y_all - y) < reach
        robots[np.arange(idx.size), idx] = False  # (not its own disc)
        return np.concatenate((circles, robots), axis=1)

    def _near_edges(self, x: FloatArray, y: FloatArray) -> IndexArray:
        """The wall edges within `horizon_m` of any robot at x, y (by their bounding
        boxes): the others' echoes could only come back at max range.
        """
        if not self.edges.ax.size:
            return np.zeros(0, dtype=np.intp)
        x0, y0, x1, y1 = self._edge_boxes
        px, py = x[:, None], y[:, None]
        out_x = np.maximum(np.maximum(x0 - px, px - x1), 0.0)
        out_y = np.maximum(np.maximum(y0 - py, py - y1), 0.0)
        near = out_x * out_x + out_y * out_y < self.horizon_m * self.horizon_m
        return np.flatnonzero(near.any(axis=0))

    def _edge_hits(self, rays: Rays, walls: IndexArray) -> FloatArray:
        """Each ray's nearest hit among wall edges `walls` (robots, rays), inf if none."""
        e = self.edges
        ex, ey, _ = e.spans
        edges = e.ax[walls], e.ay[walls], ex[walls], ey[walls]
        ox, oy, dx, dy = (a.ravel() for a in rays)
        if ox.size * walls.size <= _CHUNK:
            return nearest_segment_hits(ox, oy, dx, dy, *edges).reshape(rays[0].shape)
        out = np.empty(ox.size)
        step = max(1, _CHUNK // walls.size)
        for lo in range(0, ox.size, step):
            part = slice(lo, lo + step)
            out[part] = nearest_segment_hits(ox[part], oy[part], dx[part], dy[part], *edges)
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
            d = np.hypot(x[:, None] - circles[:, 0], y[:, None] - circles[:, 1])
            ri, k = np.nonzero(d - circles[:, 2] < self.horizon_m)
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
