"""The shapes a formation may take on the way: the scenario's own, a shrunk one (the
separations across the heading narrowed) and a column (every robot behind the leader),
and the planned transitions between them.

Which robot takes which slot of a new shape is the assignment with the least sum of
squared distances (CAPT, Turpin, Michael & Kumar, "Concurrent assignment and planning of
trajectories for multiple robots", IJRR 2014): the leader keeps its slot, and every
robot moves on a straight line in the formation frame, all at the same fraction of the
way at the same time. With the slots of both shapes at least `2 sqrt(2) R` apart, such
synchronised straight lines keep every two robots at least `2 R` apart, so no robot
crosses another's path (`tests/unit/test_shapes.py` checks every shape and size).

A shape in effect is a `ShapeKey`: the shape moved from, the shape moved to, and how far
(`morph`, 0..1; 1 = arrived). The leader decides and publishes it in its flags; every
robot computes the same slot positions from it (`ShapeBook.positions`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from functools import cached_property

from phalanx.core.formation import Formation
from phalanx.core.geometry import Vec2

SCENARIO_SHAPE = 0
SHRUNK = 1
COLUMN = 2
SHAPE_NAMES = ("scenario", "shrunk", "column")
# Slots of a reshaped formation stay at least this far apart (m): the CAPT condition
# 2 sqrt(2) R for a P3DX (R = 0.25 m) is 0.71 m.
MIN_SEPARATION_M = 0.8
# The shrunk shape narrows the separations across the heading to this share at most.
SHRINK_SHARE = 0.6
# A slide's speed rises over this share of its time, and falls over as much at its end.
RAMP_SHARE = 0.2
_MAX_ASSIGNED = 7  # robots beyond this keep the order of their along-track position


@dataclass(frozen=True, slots=True)
class ShapeKey:
    """The shape in effect: moving from shape `source` to shape `target`, `morph` of the
    way there (0..1; 1 = in `target`). Shapes: 0 scenario, 1 shrunk, 2 column.
    """

    source: int = SCENARIO_SHAPE
    target: int = SCENARIO_SHAPE
    morph: float = 1.0

    @property
    def settled(self) -> bool:
        """In a shape, not between two."""
        return self.morph >= 1.0

    def settled_in(self, shape: int) -> bool:
        """In `shape`, not on the way to or from it (whichever shape it came from)."""
        return self.settled and self.target == shape

    @property
    def current(self) -> int:
        """The shape it is in, or is moving to."""
        return self.target


NOMINAL_KEY = ShapeKey()


def slide_share(s: float) -> float:
    """How far along its straight line a slot is (0..1) `s` of a slide's time in: its
    speed rising steadily over the first `RAMP_SHARE` of the time, steady, and falling
    over the last (the slots start and stop gently, and at their fastest go 1 /
    (1 - `RAMP_SHARE`) times their mean speed).
    """
    s = min(1.0, max(0.0, s))
    f = RAMP_SHARE
    if s < f:
        return s * s / (2 * f * (1 - f))
    if s > 1 - f:
        return 1.0 - (1 - s) * (1 - s) / (2 * f * (1 - f))
    return (s - f / 2) / (1 - f)


class ShapeBook:
    """The shapes of one formation (slot positions relative to the root's slot, m)."""

    def __init__(self, formation: Formation) -> None:
        self.scenario_formation = formation
        self._cache: dict[ShapeKey, Formation] = {}

    @cached_property
    def nominal(self) -> dict[str, Vec2]:
        """The scenario's shape (worked out when first asked: a fleet that never changes
        its shape never needs it, and each of its n robots would pay O(n) for it).
        """
        formation = self.scenario_formation
        root = formation.positions[formation.root]
        return {r: p - root for r, p in formation.positions.items()}

    @cached_property
    def shapes(self) -> tuple[dict[str, Vec2], ...]:
        """Every shape's slots: scenario, shrunk, column."""
        return (self.nominal, self._shrunk(), self._column())

    def half_span_m(self, shape: int, radius_m: float) -> float:
        """Half the shape's width across its heading, plus a robot radius (m)."""
        ys = [p.y_m for p in self.shapes[shape].values()]
        return (max(ys) - min(ys)) / 2 + radius_m

    @cached_property
    def distinct(self) -> tuple[int, ...]:
        """The scenario's shape and each other with other slots than it, in the book's
        order (scenario, shrunk, column): the shapes a leader chooses among.
        """
        return tuple(s for s in range(len(self.shapes)) if s == SCENARIO_SHAPE or self.differs(s))

    def differs(self, shape: int) -> bool:
        """Whether `shape` has other slots than the scenario's."""
        return any((self.shapes[shape][r] - p).norm() > 1e-9 for r, p in self.nominal.items())

    def positions(self, key: ShapeKey) -> dict[str, Vec2]:
        """Every robot's slot under `key`: straight lines from the old shape's slots to the
        new one's, the same fraction of the way for every robot.
        """
        a, b = self.shapes[key.source], self.shapes[key.target]
        s = slide_share(key.morph)
        return {
            r: Vec2(a[r].x_m + s * (b[r].x_m - a[r].x_m), a[r].y_m + s * (b[r].y_m - a[r].y_m))
            for r in self.nominal
        }

    def formation(self, key: ShapeKey) -> Formation:
        """The formation under `key` (the same follow tree; cached per key)."""
        if key == NOMINAL_KEY:
            return self.scenario_formation
        found = self._cache.get(key)
        if found is None:
            if len(self._cache) > 512:
                self._cache.clear()
            parents = self.scenario_formation.parents
            found = Formation(positions=self.positions(key), parents=parents)
            self._cache[key] = found
        return found

    def _spacing_m(self) -> float:
        points = list(self.nominal.values())
        gaps = [(a - b).norm() for a, b in itertools.combinations(points, 2)]
        return max(MIN_SEPARATION_M, min(gaps, default=MIN_SEPARATION_M))

    def _shrunk(self) -> dict[str, Vec2]:
        """Separations across the heading narrowed as far as `SHRINK_SHARE`, but never
        below `MIN_SEPARATION_M` between two robots.
        """
        share = 1.0
        for step in range(1, 41):
            trial = 1.0 - step * (1.0 - SHRINK_SHARE) / 40
            points = [Vec2(p.x_m, p.y_m * trial) for p in self.nominal.values()]
            if _closest_m(points) < MIN_SEPARATION_M - 1e-9:
                break
            share = trial
        return {r: Vec2(p.x_m, p.y_m * share) for r, p in self.nominal.items()}

    def _column(self) -> dict[str, Vec2]:
        """Every robot in a line behind the root, the slots assigned CAPT's way."""
        root = self.scenario_formation.root
        spacing = self._spacing_m()
        followers = [r for r in self.nominal if r != root]
        slots = [Vec2(-(k + 1) * spacing, 0.0) for k in range(len(followers))]
        return {root: Vec2(0.0, 0.0), **_assign(followers, self.nominal, slots)}


def _closest_m(points: list[Vec2]) -> float:
    return min(((a - b).norm() for a, b in itertools.combinations(points, 2)), default=math.inf)


def _assign(robots: list[str], start: dict[str, Vec2], slots: list[Vec2]) -> dict[str, Vec2]:
    """The slots to robots with the least sum of squared distances (exhaustive for a few
    robots; beyond that in the order of their along-track position, then across).
    """
    if len(robots) > _MAX_ASSIGNED:
        order = sorted(robots, key=lambda r: (-start[r].x_m, abs(start[r].y_m), r))
        return dict(zip(order, slots, strict=True))
    best: tuple[float, tuple[Vec2, ...]] | None = None
    for perm in itertools.permutations(slots):
        cost = sum((start[r] - q).norm() ** 2 for r, q in zip(robots, perm, strict=True))
        if best is None or cost < best[0] - 1e-12:
            best = (cost, perm)
    assert best is not None  # noqa: S101 (at least the identity)
    return dict(zip(robots, best[1], strict=True))
