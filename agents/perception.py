"""What a robot's sonar ring says about the space around it, as geometry in its body frame.

Each reading becomes obstacle points across the transducer's beam (a sonar only knows
that something lies somewhere on the arc at that range, so the whole arc is treated as
occupied). The free way round those points and the heading to take are worked out from
them by navigation (`phalanx.agents.navigation`: `clearance`, `steering`).

numpy (the arcs' test navigation's fleet map asks, `arcs_met`, is a compiled loop doing
the same arithmetic where numba is installed: `perception_kernels`), no I/O: the same
numbers in the batch runner and on a robot. A reading's geometry (`SonarEchoes`) is
worked out for a whole fleet in one pass (`SonarGeometry.read_all`, what the batch runner
does) or for one robot (`read`, the same code on one row): elementwise arithmetic gives
each robot the same numbers either way.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import numpy.typing as npt

from phalanx.core.compiled import kernels
from phalanx.core.frozen import quick_init
from phalanx.core.geometry import Vec2
from phalanx.core.robot_params import RobotParams

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
NO_OBSTACLE_M = math.inf
_AT_MAX_RANGE_M = 1e-6
_REACH_MARGIN_M = 1e-3
_DOUBT = 1e-9
# Blind gaps between beams are filled with the neighbours' echoes within this range (m).
GAP_FILL_RANGE_M = 1.5
# Lateral spread an echo's arc is narrowed to when far (m).
ARC_SPREAD_M = 0.3
# An echo at the minimum range is taken this far outside the body's disc (m).
EDGE_MARGIN_M = 1e-3
# The compiled arcs' test (`phalanx.core.compiled`), where numba is installed.
KERNELS = "phalanx.agents.perception_kernels"


@quick_init
@dataclass(frozen=True, slots=True)
class SonarEchoes:
    """One sonar reading as geometry in the robot's body frame, before any echo is
    known to be a robot: the ranges, which transducers heard an echo short of max range
    (`echo`), the point of every ray at its transducer's range (`ray_x_m`, `ray_y_m`),
    the rays that are obstacle points of those echoes (`seen`), those points (`raw`)
    and the distance to the nearest of them (`nearest_m`, inf if none).
    """

    ranges_m: FloatArray
    echo: BoolArray
    ray_x_m: FloatArray
    ray_y_m: FloatArray
    seen: BoolArray
    raw: tuple[FloatArray, FloatArray]
    nearest_m: float
    batch: SonarBatch | None = None  # the readings read with it, in one pass


@quick_init
@dataclass(frozen=True, slots=True)
class SonarBatch:
    """Readings of several robots read in one pass: the arrays of `SonarEchoes`, a row
    per robot, and each robot's reading (views into them).
    """

    ranges_m: FloatArray
    echo: BoolArray
    ray_x_m: FloatArray
    ray_y_m: FloatArray
    seen: BoolArray
    readings: list[SonarEchoes]


def _clip(a: FloatArray, bound: FloatArray) -> FloatArray:
    """`np.clip(a, -bound, bound)`, the same arithmetic (max, then min) at a fraction of
    its call's cost on arrays this small.
    """
    out: FloatArray = np.minimum(np.maximum(a, -bound), bound)
    return out


def _flat_rows(
    x: FloatArray, y: FloatArray, keep: BoolArray
) -> tuple[FloatArray, FloatArray, list[tuple[int, int]]]:
    """The `keep` entries of x and y, row after row, and each row's (start, end) in them."""
    ends = np.cumsum(keep.sum(axis=1)).tolist()
    return x[keep], y[keep], list(zip([0, *ends[:-1]], ends, strict=True))


@quick_init
@dataclass(frozen=True, slots=True)
class MaskedEchoes:
    """A reading with the formation's own robots masked out, for robot `robot_id` at
    `t_s` (`phalanx.agents.masking`): the echoes left, their obstacle points (body
    frame) and the free way straight ahead and behind along the robot's corridor (m).
    """

    robot_id: str
    t_s: float
    echo: BoolArray
    points: tuple[FloatArray, FloatArray]
    ahead_m: float
    behind_m: float


@dataclass(frozen=True)
class SonarGeometry:
    """Beam geometry of a sonar ring: one row per transducer, and `RAYS_PER_BEAM` rays
    across each beam for the obstacle points (body frame).
    """

    unit_x_m: FloatArray
    unit_y_m: FloatArray
    unit_heading_rad: FloatArray
    half_beam_rad: float
    reach_left_rad: FloatArray
    reach_right_rad: FloatArray
    origin_x_m: FloatArray  # per ray
    origin_y_m: FloatArray
    angle_rad: FloatArray
    unit_of_ray: npt.NDArray[np.intp]
    offset_rad: FloatArray  # each ray's angle off its beam's axis
    gap_fill: BoolArray  # rays that stand in for a blind gap beside the beam
    max_range_m: float
    radius_m: float
    min_range_m: float
    edge_m: FloatArray  # per ray: range to just outside the body's disc

    @classmethod
    def from_params(cls, robot: RobotParams) -> SonarGeometry:
        """The ring of a robot parameter file.

        Each beam's rays also cover half the blind gap to each neighbouring beam (the
        P3DX's ring leaves 25 deg unseen between its 50 and 90 deg sonars): what no sonar
        sees is taken to be as near as what its neighbours see, never as free.
        The last ring built is kept for the same parameters (a fleet shares one).
        """
        if not _LAST_RING or _LAST_RING[0][0] is not robot:
            _LAST_RING[:] = [(robot, cls._build(robot))]
        return _LAST_RING[0][1]

    @classmethod
    def _build(cls, robot: RobotParams) -> SonarGeometry:
        units = robot.sonar.units
        half = math.radians(robot.sonar.beam_width_deg) / 2
        headings = [math.radians(u.heading_deg) for u in units]
        rows = []
        reach = [_reach(headings, i, half) for i in range(len(units))]
        for i, u in enumerate(units):
            left, right = reach[i]
            fan = (
                (-right, right > half),
                (-half, False),
                (0.0, False),
                (half, False),
                (left, left > half),
            )
            rows += [(u.x_m, u.y_m, headings[i] + offset, i, offset, fill) for offset, fill in fan]
        ox, oy, angle, unit, offset, fill = zip(*rows, strict=True)
        return cls(
            np.array([u.x_m for u in units]),
            np.array([u.y_m for u in units]),
            np.array(headings),
            half,
            np.array([left for left, _ in reach]),
            np.array([right for _, right in reach]),
            np.array(ox),
            np.array(oy),
            np.array(angle),
            np.array(unit, dtype=np.intp),
            np.array(offset),
            np.array(fill, dtype=bool),
            robot.sonar.max_range_m,
            robot.radius_m,
            robot.sonar.min_range_m,
            _edge_m(np.array(ox), np.array(oy), np.array(angle), robot.radius_m + EDGE_MARGIN_M),
        )

    def _unclipped(self, ray_r: FloatArray) -> FloatArray:
        """Ray ranges with a minimum-range reading moved in to the body's edge.

        A sonar reads its minimum range for anything nearer, down to the transducer:
        such an echo may be as near as the body itself (on the P3DX's rear ring, 9.6 cm
        nearer than it reads), and is taken to be, so nothing drives into what it hides.
        """
        return np.where(ray_r <= self.min_range_m, np.minimum(ray_r, self.edge_m), ray_r)

    def points(
        self, ranges_m: Sequence[float] | FloatArray, known: Sequence[tuple[Vec2, float]] = ()
    ) -> tuple[FloatArray, FloatArray]:
        """Obstacle points (x, y in m, body frame) of a reading.

        Max-range readings carry no echo. An echo whose arc passes within a `known`
        `(centre, radius_m)` disc (a robot of the formation) is that robot, not an
        obstacle, and is dropped whole: a sonar cannot tell where on its arc it was hit.
        """
        ranges = np.asarray(ranges_m, dtype=np.float64)
        return self.points_of(ranges, self.echoes(ranges, known))

    def points_of(self, ranges: FloatArray, echo: BoolArray) -> tuple[FloatArray, FloatArray]:
        """Obstacle points of the transducers `echo` marks (see `echoes`)."""
        if not echo.any():  # (also a reading short of the ring: `echoes` marks none)
            return np.zeros(0), np.zeros(0)
        r = self._unclipped(ranges[self.unit_of_ray])
        # A blind gap is assumed as near as its neighbour only close by, where it matters
        # for safety; far off it would close every opening the robot aims for.
        seen = echo[self.unit_of_ray] & (~self.gap_fill | (r < GAP_FILL_RANGE_M))
        if not seen.any():
            return np.zeros(0), np.zeros(0)
        # Far off, the beam's arc is narrowed to `ARC_SPREAD_M` across: a wall's edge
        # grazed by the side of a beam 4 m off would otherwise seem to close a doorway.
        # Closer in the arc widens again, so what is really there is seen in time.
        spread = np.arctan2(ARC_SPREAD_M, np.maximum(r, 1e-6))
        offset = np.where(self.gap_fill, self.offset_rad, _clip(self.offset_rad, spread))
        angle = self.angle_rad - self.offset_rad + offset
        x = self.origin_x_m + r * np.cos(angle)
        y = self.origin_y_m + r * np.sin(angle)
        return x[seen], y[seen]

    def read(self, ranges_m: Sequence[float] | FloatArray) -> SonarEchoes:
        """The geometry of one reading (`read_all` of one row; one short of the ring: no echo)."""
        ranges = np.asarray(ranges_m, dtype=np.float64)
        units = self.unit_x_m.size
        if ranges.size < units:
            return self.read_all(np.full((1, units), self.max_range_m), full=[ranges]).readings[0]
        return self.read_all(ranges[None, :units], full=[ranges]).readings[0]

    def read_all(
        self, ranges_m: FloatArray, *, full: Sequence[FloatArray] | None = None
    ) -> SonarBatch:
        """The geometry of every robot's reading, rows of `ranges_m` (robots, transducers),
        worked out in one pass: the arithmetic of `echoes` and `points_of`, row by row.
        `full`: the readings as the robots gave them (each reading's `ranges_m`).
        """
        r = np.asarray(ranges_m, dtype=np.float64)
        echo = self.ranged(r)
        ray_r = self._unclipped(r[:, self.unit_of_ray])
        seen = echo[:, self.unit_of_ray] & (~self.gap_fill | (ray_r < GAP_FILL_RANGE_M))
        spread = np.arctan2(ARC_SPREAD_M, np.maximum(ray_r, 1e-6))
        offset = np.where(self.gap_fill, self.offset_rad, _clip(self.offset_rad, spread))
        angle = self.angle_rad - self.offset_rad + offset
        x = self.origin_x_m + ray_r * np.cos(angle)
        y = self.origin_y_m + ray_r * np.sin(angle)
        near = np.sqrt(np.where(seen, x * x + y * y, np.inf).min(axis=1)).tolist()
        batch = SonarBatch(r, echo, x, y, seen, [])
        rows = full if full is not None else r
        xs, ys, bounds = _flat_rows(x, y, seen)
        batch.readings.extend(
            SonarEchoes(rows[i], echo[i], x[i], y[i], seen[i], (xs[a:b], ys[a:b]), near[i], batch)
            for i, (a, b) in enumerate(bounds)
        )
        return batch

    def ranged(self, ranges_m: FloatArray) -> BoolArray:
        """Per range: whether something was there, short of the sonar's maximum range
        (an obstacle, or one of the formation's robots that `echoes` leaves out).
        """
        short: BoolArray = ranges_m < self.max_range_m - _AT_MAX_RANGE_M
        return short

    def echoes(self, ranges: FloatArray, known: Sequence[tuple[Vec2, float]] = ()) -> BoolArray:
        """Per transducer: an echo (short of max range) that is not one of the `known`
        discs (see `points`). A reading with fewer ranges than the ring has transducers
        (a robot whose sonar is not as its parameter file says) has no echo at all.
        """
        if ranges.size < self.unit_x_m.size:
            return np.zeros(self.unit_x_m.size, dtype=bool)
        r = ranges[: self.unit_x_m.size]
        echo = self.ranged(r)
        if not known or not echo.any():
            return echo
        reach_m = float(self.reach_m(r, echo))
        near = [(c, rad) for c, rad in known if math.hypot(c.x_m, c.y_m) - rad < reach_m]
        if near:
            echo &= ~self.arcs_meet(r, near).any(axis=0)
        return echo

    def arcs_meet(self, r: FloatArray, discs: Sequence[tuple[Vec2, float]]) -> BoolArray:
        """Per disc (row) and transducer (column): whether the transducer's echo arc at
        range `r` passes within the disc (`(centre, radius_m)`, body frame).
        """
        cx = np.array([[c.x_m] for c, _ in discs])
        cy = np.array([[c.y_m] for c, _ in discs])
        radius = np.array([[rad] for _, rad in discs])
        return self.arcs_meet_at(r, cx, cy, radius, self.nearest_dirs(cx, cy))

    def nearest_dirs(self, cx: FloatArray, cy: FloatArray) -> tuple[FloatArray, FloatArray]:
        """For discs centred at `cx`, `cy` (columns, body frame), the unit direction from
        each transducer to the point of its beam (as far as it is taken to reach) nearest
        each disc's centre: what `arcs_meet` needs that does not depend on the range, so
        discs that stay put in the body frame (the formation's slots) can keep it.
        """
        towards = np.arctan2(cy - self.unit_y_m, cx - self.unit_x_m)
        off = np.mod(towards - self.unit_heading_rad + math.pi, 2.0 * math.pi) - math.pi
        nearest = self.unit_heading_rad + np.minimum(
            np.maximum(off, -self.reach_right_rad), self.reach_left_rad
        )
        return np.cos(nearest), np.sin(nearest)

    def arcs_meet_at(
        self,
        r: FloatArray,
        cx: FloatArray,
        cy: FloatArray,
        radius: FloatArray | float,
        dirs: tuple[FloatArray, FloatArray],
    ) -> BoolArray:
        """`arcs_meet` given the discs' `nearest_dirs`."""
        dx = self.unit_x_m + r * dirs[0] - cx
        dy = self.unit_y_m + r * dirs[1] - cy
        # hypot (slow) only where the squared distance leaves the answer in doubt: a hair
        # either side of the radius, far wider than either's rounding
        d2, r2 = dx * dx + dy * dy, np.square(radius)
        meets: BoolArray = d2 < r2 * (1.0 - _DOUBT)
        doubt = ~meets & (d2 <= r2 * (1.0 + _DOUBT))
        if doubt.any():
            near = np.broadcast_to(radius, d2.shape)[doubt]
            meets[doubt] = np.hypot(dx[doubt], dy[doubt]) < near
        return meets

    def arcs_met(
        self,
        r: FloatArray,
        owner: npt.NDArray[np.intp],
        centres: tuple[FloatArray, FloatArray],
        radius_m: float,
        dirs: tuple[FloatArray, FloatArray],
        met: BoolArray,
        *,
        compiled: bool = True,
    ) -> None:
        """Mark in `met` (rows of `r`: readings x transducers) each transducer whose echo
        arc meets a disc of `radius_m` its reading owns: disc k at `centres` (x, y; row k
        of each, body frame) owned by reading `owner[k]` (ascending), with its
        `nearest_dirs`. `arcs_meet_at`, disc by disc; with `compiled`, the compiled loop's
        where numba is (the fleet map's question, asked only where a robot navigates).
        """
        if owner.size == 0:
            return
        cx, cy = centres
        loop = kernels(KERNELS) if compiled else None
        if loop is not None:
            r2 = np.square(radius_m)
            c = np.ascontiguousarray  # (one kind of array each: one compiled signature)
            loop.arcs_met(
                (self.unit_x_m, self.unit_y_m), c(r),
                (c(owner), c(cx.reshape(-1)), c(cy.reshape(-1)), c(dirs[0]), c(dirs[1])),
                (radius_m, r2 * (1.0 - _DOUBT), r2 * (1.0 + _DOUBT)), met,
            )  # fmt: skip
            return
        hit = self.arcs_meet_at(r[owner], cx, cy, radius_m, dirs)
        starts = np.flatnonzero(np.concatenate(([True], owner[1:] != owner[:-1])))
        met[owner[starts]] |= np.logical_or.reduceat(hit, starts, axis=0)

    @cached_property
    def mount_m(self) -> float:
        """The furthest transducer from the body origin (m)."""
        return float(np.hypot(self.unit_x_m, self.unit_y_m).max())

    def reach_m(self, ranges_m: FloatArray, echo: BoolArray) -> FloatArray:
        """Per reading (the last axis its transducers): how far from the body origin
        (m) its echoes' arcs can reach, the furthest transducer's mount plus the longest
        echo, with a margin that keeps rounding on the safe side. A disc wholly beyond it
        is met by no echo's arc.
        """
        longest = np.where(echo, ranges_m, 0.0).max(axis=-1)
        reach: FloatArray = self.mount_m + longest + _REACH_MARGIN_M
        return reach


_LAST_RING: list[tuple[RobotParams, SonarGeometry]] = []


def _edge_m(x_m: FloatArray, y_m: FloatArray, angle_rad: FloatArray, radius_m: float) -> FloatArray:
    """Per ray from (`x_m`, `y_m`) along `angle_rad`: the distance out to a circle of
    `radius_m` about the body origin (0 from a transducer outside it: nothing lies
    between it and what it hears).
    """
    along = x_m * np.cos(angle_rad) + y_m * np.sin(angle_rad)
    inside = radius_m * radius_m - x_m * x_m - y_m * y_m
    out = -along + np.sqrt(np.maximum(along * along + inside, 0.0))
    return np.asarray(np.where(inside > 0.0, out, 0.0))


def _reach(headings: Sequence[float], i: int, half_beam_rad: float) -> tuple[float, float]:
    """How far beam `i` is taken to reach (left, right of its axis, rad): its half-width
    plus half of any blind gap to the nearest beam on that side.
    """
    h = headings[i]
    offsets = [
        (other - h + math.pi) % (2.0 * math.pi) - math.pi
        for j, other in enumerate(headings)
        if j != i
    ]
    left = min((o for o in offsets if o > 1e-9), default=2.0 * half_beam_rad)
    right = min((-o for o in offsets if o < -1e-9), default=2.0 * half_beam_rad)
    return (
        half_beam_rad + max(0.0, left / 2 - half_beam_rad),
        half_beam_rad + max(0.0, right / 2 - half_beam_rad),
    )


def nearest_m(points: tuple[FloatArray, FloatArray]) -> float:
    """Distance from the body origin to the nearest point (inf if none)."""
    x, y = points
    return float(np.sqrt(np.min(x * x + y * y))) if x.size else NO_OBSTACLE_M


def braking_gap_m(speed_mps: float, *, decel_mps2: float, latency_s: float) -> float:
    """Distance covered while a command to stop takes effect and the robot brakes."""
    v = abs(speed_mps)
    return v * latency_s + v * v / (2.0 * decel_mps2)
