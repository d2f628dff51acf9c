"""Free way round a robot, from its sonar's obstacle points (body frame, m): how far a
straight corridor as wide as the robot (plus a margin) can go along any heading before
it touches one, for the robot alone or for a whole formation moving together, and the
navigator's candidate headings that steering picks among.

numpy, or one compiled loop where numba is installed (`clearance_kernels`, the same
floats to the bit); no I/O.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from phalanx.agents.perception import NO_OBSTACLE_M, FloatArray
from phalanx.core.compiled import kernels
from phalanx.core.frozen import quick_init
from phalanx.core.geometry import Vec2

IntArray = npt.NDArray[np.intp]

# Candidate headings of the reactive navigator, body frame: every 7.5 deg all round.
HEADINGS_RAD: FloatArray = np.radians(np.arange(-180.0, 180.0, 7.5))
# The compiled pass (`phalanx.core.compiled`), where numba is installed.
KERNELS = "phalanx.agents.navigation.clearance_kernels"


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
    x, y = (np.asarray(a, dtype=np.float64) for a in points)
    out = np.full(headings_rad.shape, NO_OBSTACLE_M)
    if x.size == 0 or headings_rad.size == 0 or not origins:
        return out
    w2 = half_width_m * half_width_m
    compiled = kernels(KERNELS)
    if compiled is not None:
        headings = np.asarray(headings_rad, dtype=np.float64)
        nearest: FloatArray = compiled.corridor(
            np.ascontiguousarray(x), np.ascontiguousarray(y), np.cos(headings),
            np.sin(headings), np.array([o.x_m for o in origins], dtype=np.float64),
            np.array([o.y_m for o in origins], dtype=np.float64), w2, turning,
        )  # fmt: skip
        return np.minimum(out, nearest, out=out) if turning else nearest
    if not turning:
        return _sliding(x, y, headings_rad, origins, w2)
    view = _VIEWS.of(x, y, headings_rad)
    slots = [o for o in origins if o.x_m != 0.0 or o.y_m != 0.0]
    if len(slots) < len(origins):
        out = np.minimum(out, view.own(w2))
    if slots:
        out = np.minimum(out, view.turned(slots, w2))
    return out


class _View:
    """Points (body frame) along and across a set of headings, for every disc turned to
    face them.

    The robot's own disc's pass reads the points' components as they are. A slot's
    disc, turned to face the heading, has its own coordinates as its components, so the
    points' components less the slot's pick the pairs that can count, with a margin far
    wider than their rounding (`hair_m`); only those pairs are then worked out as the
    components of `p - o`, as the slot's own pass would, to the bit.
    """

    def __init__(self, x: FloatArray, y: FloatArray, headings_rad: FloatArray) -> None:
        self.x, self.y = x.copy(), y.copy()  # (the caller may write over its own)
        self.c, self.s = np.cos(headings_rad), np.sin(headings_rad)
        self.along, self.across = _components(x, y, self.c[:, None], self.s[:, None])
        self._own: dict[float, FloatArray] = {}

    @functools.cached_property
    def hair_m(self) -> float:
        """A margin far wider than the rounding of the points' components (a few units
        in the last place of their size); infinite (every pair a candidate) for points
        that are not all finite.
        """
        size_m = float(np.abs(self.x).max()) + float(np.abs(self.y).max())
        return 1e-9 * (1.0 + size_m) if math.isfinite(size_m) else math.inf

    def own(self, w2: float) -> FloatArray:
        """The pass of the disc at the origin (the robot's own), kept per width."""
        got = self._own.get(w2)
        if got is None:
            got = self._own[w2] = _plain_pass(self.along, self.across, w2)
        return got

    def turned(self, slots: Sequence[Vec2], w2: float) -> FloatArray:
        """Per heading, the first touch of any disc at `slots`, turned to face it: one
        pass, a row for each (slot, heading).
        """
        k, (n, m) = len(slots), self.along.shape
        xs, ys = [o.x_m for o in slots], [o.y_m for o in slots]
        hair_m = self.hair_m * (1.0 + max(map(abs, xs)) + max(map(abs, ys)))
        reach_m = math.sqrt(w2) + hair_m
        ox, oy = np.array(xs), np.array(ys)
        shape = (k, n * m)
        picked = _SCRATCH.flags(shape).reshape(k, n, m)
        also = _SCRATCH.flags(shape, second=True).reshape(k, n, m)
        np.greater(self.across[None], (oy - reach_m)[:, None, None], out=picked)
        picked &= np.less(self.across[None], (oy + reach_m)[:, None, None], out=also)
        picked &= np.greater(self.along[None], (ox - hair_m)[:, None, None], out=also)
        row, col = _rows_and_columns(np.flatnonzero(picked), m)  # row: slot * n + heading
        _, heading = _rows_and_columns(row, n)
        # each slot's place turned with each heading, a row per (slot, heading)
        c, s, sx, sy = self.c, self.s, ox[:, None], oy[:, None]
        placed_x = (c * sx - s * sy).reshape(-1)
        placed_y = (s * sx + c * sy).reshape(-1)
        f, lat = _components(
            self.x[col] - placed_x[row], self.y[col] - placed_y[row], c[heading], s[heading]
        )
        lat2 = lat * lat
        # (a candidate outside the corridor, or behind the disc, never touches)
        hit = np.where((lat2 < w2) & (f > 0.0), _touch(f, lat2, w2), np.inf)
        out: FloatArray = _row_least(row, hit, k * n).reshape(k, n).min(axis=0)
        return out


def _sliding(
    x: FloatArray, y: FloatArray, headings_rad: FloatArray, origins: Sequence[Vec2], w2: float
) -> FloatArray:
    """Per heading, the first touch of any disc at `origins` sliding along it unturned:
    one pass, a row for each (disc, heading).
    """
    n, k = headings_rad.size, len(origins)
    ox = np.array([o.x_m for o in origins])[:, None, None]
    oy = np.array([o.y_m for o in origins])[:, None, None]
    c, s = np.cos(headings_rad)[:, None], np.sin(headings_rad)[:, None]
    along, across = _components(x - ox, y - oy, c, s)  # (disc, heading, point)
    nearest = _plain_pass(along.reshape(k * n, -1), across.reshape(k * n, -1), w2)
    out: FloatArray = nearest.reshape(k, n).min(axis=0)
    return out


def _components(
    dx: FloatArray, dy: FloatArray, c: FloatArray | float, s: FloatArray | float
) -> tuple[FloatArray, FloatArray]:
    """The components of offsets (`dx`, `dy`) along and across the heading of cosine `c`
    and sine `s`: the plain pass's arithmetic, one place for all its uses.
    """
    return dx * c + dy * s, dy * c - dx * s


def _plain_pass(along: FloatArray, across: FloatArray, w2: float) -> FloatArray:
    """Per row, the first touch of the disc at the origin of the points' components
    `along` and `across` the row's heading.
    """
    shape = along.shape
    lat2 = np.multiply(across, across, out=_SCRATCH.floats(shape))
    inside = np.less(lat2, w2, out=_SCRATCH.flags(shape))
    inside &= np.greater(along, 0.0, out=_SCRATCH.flags(shape, second=True))
    pairs = np.flatnonzero(inside)
    if pairs.size == 0:
        return np.full(shape[0], np.inf)
    hit = _touch(along.reshape(-1)[pairs], lat2.reshape(-1)[pairs], w2)
    return _row_least(pairs // shape[1], hit, shape[0])


def _rows_and_columns(flat: IntArray, columns: int) -> tuple[IntArray, IntArray]:
    """The rows and columns of flat indices into an array of `columns` columns
    (`np.divmod`, in cheaper integer arithmetic).
    """
    row = flat // columns
    return row, flat - row * columns


def _touch(f: FloatArray, lat2: FloatArray, w2: float) -> FloatArray:
    """`f - sqrt(w2 - lat2)`, floored at 0: where a disc of squared radius `w2` moving
    along a heading first touches a point inside its corridor and ahead of its centre,
    of components `f` along and `lat2` (squared) across the heading.
    """
    touch: FloatArray = np.maximum(f - np.sqrt(np.maximum(w2 - lat2, 0.0)), 0.0)
    return touch


def _row_least(row: IntArray, hit: FloatArray, rows: int) -> FloatArray:
    """Per row (of `rows`), the least of the `hit`s in it; inf where none is."""
    nearest = np.full(rows, np.inf)
    np.minimum.at(nearest, row, hit)
    return nearest


class _Views(threading.local):
    """The last `_View`, one per thread: a navigating leader asks about the same points
    and headings for the robot alone and for the whole shape. Reused only for points
    and headings equal to the bit.
    """

    def __init__(self) -> None:
        self._key: tuple[bytes, bytes, bytes] | None = None
        self._view: _View | None = None

    def of(self, x: FloatArray, y: FloatArray, headings_rad: FloatArray) -> _View:
        """The view of these points along these headings."""
        headings = np.asarray(headings_rad, np.float64)
        key = (x.tobytes(), y.tobytes(), headings.tobytes())
        if self._view is None or key != self._key:
            self._view, self._key = _View(x, y, headings), key
        return self._view


class _Scratch(threading.local):
    """Work arrays kept from call to call, one set per thread: a pass makes arrays of
    headings x points (about 100 kB), and fresh ones that size cost page faults.
    """

    def __init__(self) -> None:
        self._floats: FloatArray = np.empty(0)
        self._flags: npt.NDArray[np.bool_] = np.empty(0, dtype=bool)

    def floats(self, shape: tuple[int, int]) -> FloatArray:
        """A float array of `shape` (its contents left over)."""
        size = shape[0] * shape[1]
        if self._floats.size < size:
            self._floats = np.empty(2 * size)
        return self._floats[:size].reshape(shape)

    def flags(self, shape: tuple[int, int], *, second: bool = False) -> npt.NDArray[np.bool_]:
        """A boolean array of `shape` (its contents left over); `second`, another one."""
        size = shape[0] * shape[1]
        if self._flags.size < 2 * size:
            self._flags = np.empty(4 * size, dtype=bool)
        return self._flags[size if second else 0 :][:size].reshape(shape)


_VIEWS = _Views()
_SCRATCH = _Scratch()


def clearance_along(
    points: tuple[FloatArray, FloatArray], heading_rad: float, *, half_width_m: float
) -> float:
    """`corridor_clearance` of the robot alone along one heading (the fast path)."""
    x, y = points
    if x.size == 0:
        return NO_OBSTACLE_M
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    f, lat = _components(x, y, c, s)
    lat2 = lat * lat
    w2 = half_width_m * half_width_m
    ahead = ((lat2 < w2) & (f > 0.0)).nonzero()[0]  # inside the corridor, ahead
    if ahead.size == 0:
        return NO_OBSTACLE_M
    gaps = f[ahead] - np.sqrt(w2 - lat2[ahead])
    return max(0.0, float(np.minimum.reduce(gaps)))


def open_side(points: tuple[FloatArray, FloatArray], *, half_width_m: float) -> int:
    """+1 if the left half (counter-clockwise) is freer than the right, else -1."""
    clear = np.minimum(corridor_clearance(points, HEADINGS_RAD, half_width_m=half_width_m), 5.0)
    left = float(clear[HEADINGS_RAD > 0.0].sum())
    right = float(clear[HEADINGS_RAD < 0.0].sum())
    return 1 if left >= right else -1


def heading_offsets_rad(heading_rad: float) -> FloatArray:
    """How far each candidate heading (`HEADINGS_RAD`) lies from `heading_rad` (body
    frame, any number of turns), either way round (0 to pi).
    """
    off: FloatArray = np.abs(np.mod(HEADINGS_RAD - heading_rad + math.pi, 2 * math.pi) - math.pi)
    return off


def heading_index(heading_rad: float) -> int:
    """Index of the candidate heading (`HEADINGS_RAD`) nearest `heading_rad` (body
    frame, any number of turns).
    """
    return int(np.argmin(heading_offsets_rad(heading_rad)))


AHEAD_INDEX = heading_index(0.0)


@quick_init
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
