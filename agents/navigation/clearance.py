"""Free way round a robot, from its sonar's obstacle points (body frame, m): how far a
straight corridor as wide as the robot (plus a margin) can go along any heading before
it touches one, for the robot alone or for a whole formation moving together, and the
navigator's candidate headings that steering picks among.

Pure numpy, no I/O.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

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
    if x.size == 0 or headings_rad.size == 0:
        return out
    c, s = np.cos(headings_rad)[:, None], np.sin(headings_rad)[:, None]
    w2 = half_width_m * half_width_m
    slots = [o for o in origins if o.x_m != 0.0 or o.y_m != 0.0]
    if len(slots) < len(origins):  # the robot's own disc
        out = np.minimum(out, _OWN_PASS.nearest(x, y, headings_rad, c, s, w2))
    # the other slots' discs: a pass each, or few rows (sliding sideways) in one pass;
    # the slot rotates with the formation (origin o is given for heading 0)
    group = max(1, _FEW_ROWS // c.shape[0])
    for first in range(0, len(slots), group):
        some = slots[first : first + group]
        ox = [c * o.x_m - s * o.y_m if turning else np.full_like(c, o.x_m) for o in some]
        oy = [s * o.x_m + c * o.y_m if turning else np.full_like(s, o.y_m) for o in some]
        rows = (np.concatenate(ox), np.concatenate(oy))
        tiled = (np.tile(c, (len(some), 1)), np.tile(s, (len(some), 1)))
        nearest = _nearest_touch(x, y, rows, *tiled, w2).reshape(len(some), -1)
        out = np.minimum(out, nearest.min(axis=0))
    return out


# Slots whose passes have no more rows (slot x heading) than this share one pass.
_FEW_ROWS = 16


def _nearest_touch(
    x: FloatArray,
    y: FloatArray,
    centre: tuple[FloatArray, FloatArray] | None,
    c: FloatArray,
    s: FloatArray,
    w2: float,
) -> FloatArray:
    """Per heading (row of `c`, `s`), the least `f - sqrt(w2 - l^2)` (floored at 0) over
    the points inside the corridor and ahead of the disc's `centre` (per heading; None:
    the origin); inf where none is. The chord is worked out only for those pairs (a few).
    """
    shape = (c.shape[0], x.size)
    f, lat, term, dx, dy = _SCRATCH.floats(5, shape)
    if centre is None:
        dx, dy = x[None, :], y[None, :]
    else:
        np.subtract(x[None, :], centre[0], out=dx)
        np.subtract(y[None, :], centre[1], out=dy)
    np.multiply(dx, c, out=f)
    np.add(f, np.multiply(dy, s, out=term), out=f)
    np.multiply(dy, c, out=lat)  # lat = -dx * s + dy * c (the same bits: a - b is a + (-b))
    np.subtract(lat, np.multiply(dx, s, out=term), out=lat)
    lat2 = np.multiply(lat, lat, out=lat)
    ahead = np.less(lat2, w2, out=_SCRATCH.flags(shape))
    ahead &= np.greater(f, 0.0, out=_SCRATCH.flags(shape, second=True))
    pairs = np.flatnonzero(ahead)
    nearest = np.full(shape[0], np.inf)
    if pairs.size == 0:
        return nearest
    half_chord = np.sqrt(np.maximum(w2 - lat2.reshape(-1)[pairs], 0.0))
    hit = np.maximum(f.reshape(-1)[pairs] - half_chord, 0.0)
    row = pairs // shape[1]
    starts = np.flatnonzero(np.concatenate(([True], row[1:] != row[:-1])))
    nearest[row[starts]] = np.minimum.reduceat(hit, starts)
    return nearest


class _LastOwnPass:
    """The pass of the disc at the body's centre (origin 0) from the last call, kept for
    the next: a navigating leader asks for it with the same points for the robot alone,
    as the first slot of the whole shape and sliding sideways (two of the same
    headings). Reused only for points, width and headings equal to the bit.
    """

    def __init__(self) -> None:
        self._last: tuple[FloatArray, FloatArray, float, dict[int, int], FloatArray] | None = None

    def nearest(
        self,
        x: FloatArray,
        y: FloatArray,
        headings_rad: FloatArray,
        c: FloatArray,
        s: FloatArray,
        w2: float,
    ) -> FloatArray:
        """`_nearest_touch` of the disc at the origin, from the last call if it had the
        points, the width and every heading.
        """
        if headings_rad.dtype != np.float64:
            return _nearest_touch(x, y, None, c, s, w2)
        last = self._last  # (one read: another thread may replace it meanwhile)
        bits = np.ascontiguousarray(headings_rad).view(np.int64).tolist()
        if last is not None and last[2] == w2 and _same(last[0], x) and _same(last[1], y):
            rows = [last[3].get(b, -1) for b in bits]
            if min(rows, default=0) >= 0:
                return last[4][rows]
        nearest = _nearest_touch(x, y, None, c, s, w2)
        nearest.flags.writeable = False
        self._last = (x.copy(), y.copy(), w2, {b: i for i, b in enumerate(bits)}, nearest)
        return nearest


def _same(a: FloatArray, b: FloatArray) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


class _Scratch(threading.local):
    """Work arrays kept from call to call, one set per thread: a pass makes arrays of
    headings x points (about 100 kB), and fresh ones that size cost page faults.
    """

    def __init__(self) -> None:
        self._floats: FloatArray = np.empty(0)
        self._flags: npt.NDArray[np.bool_] = np.empty(0, dtype=bool)

    def floats(self, count: int, shape: tuple[int, int]) -> list[FloatArray]:
        """`count` float arrays of `shape` (their contents left over)."""
        size = shape[0] * shape[1]
        if self._floats.size < count * size:
            self._floats = np.empty(2 * count * size)
        return [self._floats[i * size : (i + 1) * size].reshape(shape) for i in range(count)]

    def flags(self, shape: tuple[int, int], *, second: bool = False) -> npt.NDArray[np.bool_]:
        """A boolean array of `shape` (its contents left over); `second`, another one."""
        size = shape[0] * shape[1]
        if self._flags.size < 2 * size:
            self._flags = np.empty(4 * size, dtype=bool)
        return self._flags[size if second else 0 :][:size].reshape(shape)


_OWN_PASS = _LastOwnPass()
_SCRATCH = _Scratch()


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
