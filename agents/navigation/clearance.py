"""Free way round a robot, from its sonar's obstacle points (body frame, m): how far a
straight corridor as wide as the robot (plus a margin) can go along any heading before
it touches one, for the robot alone or for a whole formation moving together, and the
navigator's candidate headings that steering picks among.

Pure numpy, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from phalanx.agents.perception import NO_OBSTACLE_M, FloatArray
from phalanx.core.geometry import Vec2

# Candidate headings of the reactive navigator, body frame: every 7.5 deg all round.
HEADINGS_RAD: FloatArray = np.radians(np.arange(-180.0, 180.0, 7.5))


def corridor_clearance(
    points: tuple[FloatArray, FloatArray],
    headings_rad: FloatArray,
    *,
    half_width_m: float,
    origins: Sequence[Vec2] = (Vec2(0.0, 0.0),),
    turning: bool = True,
) -> FloatArray:
    """Free distance (m) along each heading before a disc of radius `half_width_m` at any
    of `origins` (body frame; the formation's slots, all moving together) touches a point.
    With `turning`, the shape is first turned to face each heading (it drives that way);
    without, it slides that way as it stands.

    A disc at `o` moving along unit `u` touches point `p` after `f - sqrt(w^2 - l^2)`,
    with `f`, `l` the along and across components of `p - o` and `w` the half-width;
    a point already inside the disc gives 0 along the headings it lies ahead of (`f > 0`);
    a point behind the disc's centre never counts, so one the disc already overlaps there
    (an echo at the body's edge) leaves every way away from it open.
    """
    x, y = points
    out = np.full(headings_rad.shape, NO_OBSTACLE_M)
    if x.size == 0:
        return out
    c, s = np.cos(headings_rad)[:, None], np.sin(headings_rad)[:, None]
    w2 = half_width_m * half_width_m
    for o in origins:
        # the slot rotates with the formation: origin o is given for heading 0
        ox = c * o.x_m - s * o.y_m if turning else np.full_like(c, o.x_m)
        oy = s * o.x_m + c * o.y_m if turning else np.full_like(s, o.y_m)
        dx, dy = x[None, :] - ox, y[None, :] - oy
        f = dx * c + dy * s
        lat = -dx * s + dy * c
        inside = lat * lat < w2
        half_chord = np.sqrt(np.maximum(w2 - lat * lat, 0.0))
        ahead = inside & (f > 0.0)
        hit = np.where(ahead, np.maximum(f - half_chord, 0.0), np.inf)
        out = np.minimum(out, hit.min(axis=1))
    return out


def clearance_along(
    points: tuple[FloatArray, FloatArray], heading_rad: float, *, half_width_m: float
) -> float:
    """`corridor_clearance` of the robot alone along one heading (the fast path)."""
    x, y = points
    if x.size == 0:
        return NO_OBSTACLE_M
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    f = x * c + y * s
    lat2 = np.square(y * c - x * s)
    w2 = half_width_m * half_width_m
    half_chord = np.sqrt(np.maximum(w2 - lat2, 0.0))
    ahead = (lat2 < w2) & (f > 0.0)
    if not ahead.any():
        return NO_OBSTACLE_M
    return max(0.0, float(np.min(f[ahead] - half_chord[ahead])))


def open_side(points: tuple[FloatArray, FloatArray], *, half_width_m: float) -> int:
    """+1 if the left half (counter-clockwise) is freer than the right, else -1."""
    clear = np.minimum(corridor_clearance(points, HEADINGS_RAD, half_width_m=half_width_m), 5.0)
    left = float(clear[HEADINGS_RAD > 0.0].sum())
    right = float(clear[HEADINGS_RAD < 0.0].sum())
    return 1 if left >= right else -1


def heading_index(heading_rad: float) -> int:
    """Index of the candidate heading (`HEADINGS_RAD`) nearest `heading_rad` (body
    frame, any number of turns).
    """
    off = np.abs(np.mod(HEADINGS_RAD - heading_rad + math.pi, 2 * math.pi) - math.pi)
    return int(np.argmin(off))


AHEAD_INDEX = heading_index(0.0)


@dataclass(frozen=True, slots=True)
class Clearances:
    """Free distance (m) along every candidate heading, the formation's and own; and the
    formation's free room sliding sideways, left and right (for centring).
    """

    wide: FloatArray
    narrow: FloatArray
    left_m: float = math.inf
    right_m: float = math.inf

    def ahead_m(self) -> float:
        """Own free distance straight ahead."""
        return float(self.narrow[AHEAD_INDEX])

    def along_m(self, heading_rad: float) -> float:
        """Own free distance along the candidate heading nearest `heading_rad`."""
        return float(self.narrow[heading_index(heading_rad)])
