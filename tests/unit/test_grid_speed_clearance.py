"""`corridor_clearance`'s fast paths (numpy's, and the compiled loop numba runs) give
what the plain pass over every (slot, heading, point) gives, bit for bit, also for points
on a slot's corridor's edge (where the numpy path's pick of candidates could err) and for
points that are not finite; and the numpy path's memory of the points' projections never
outlives the points it was worked out for. The plain pass is kept here as the reference.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from phalanx.agents.navigation import HEADINGS_RAD, corridor_clearance
from phalanx.agents.perception import NO_OBSTACLE_M
from phalanx.core.compiled import chosen
from phalanx.core.geometry import Vec2

Floats = npt.NDArray[np.float64]
SIDEWAYS_RAD = np.array([np.pi / 2, -np.pi / 2])
# Every test runs on both paths (the dev extra installs numba: CI runs the compiled one).
both_paths = pytest.mark.parametrize("kind", ["numpy", "numba"])


def ref_clearance(
    points: tuple[Floats, Floats],
    headings_rad: Floats,
    *,
    half_width_m: float,
    origins: Sequence[Vec2] = (Vec2(0.0, 0.0),),
    turning: bool = True,
) -> Floats:
    x, y = points
    out = np.full(headings_rad.shape, NO_OBSTACLE_M)
    if x.size == 0:
        return out
    c, s = np.cos(headings_rad)[:, None], np.sin(headings_rad)[:, None]
    w2 = half_width_m * half_width_m
    for o in origins:
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


@st.composite
def echoes(draw: st.DrawFn) -> tuple[Floats, Floats]:
    """Points round a robot (m, body frame): scattered, some on the axes, some repeated."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    n = draw(st.integers(0, 300))
    x, y = rng.normal(0.0, draw(st.floats(0.2, 4.0)), (2, n))
    x[: n // 5] = 0.0
    y[n // 5 : n // 4] = 0.0
    x[n // 2 : n // 2 + n // 8] = x[: n // 8]
    y[n // 2 : n // 2 + n // 8] = y[: n // 8]
    return x, y


slots = st.lists(
    st.builds(Vec2, st.floats(-3.0, 3.0), st.floats(-3.0, 3.0)), min_size=0, max_size=4
)


@both_paths
@settings(max_examples=300, deadline=None)
@given(echoes(), slots, st.floats(0.05, 1.2), st.booleans(), st.booleans())
def test_clearances_are_the_plain_passes_to_the_bit(
    kind: str,
    points: tuple[Floats, Floats],
    others: list[Vec2],
    half_width_m: float,
    turning: bool,
    sideways: bool,
) -> None:
    headings = SIDEWAYS_RAD if sideways else HEADINGS_RAD
    origins = [Vec2(0.0, 0.0), *others]
    for where in ((Vec2(0.0, 0.0),), origins, others):
        with chosen(kind):
            fast = corridor_clearance(
                points, headings, half_width_m=half_width_m, origins=where, turning=turning
            )
        plain = ref_clearance(
            points, headings, half_width_m=half_width_m, origins=where, turning=turning
        )
        assert fast.tobytes() == plain.tobytes()


def _same_as_plain(
    kind: str,
    points: tuple[Floats, Floats],
    headings: Floats,
    half_width_m: float,
    origins: Sequence[Vec2] = (Vec2(0.0, 0.0),),
) -> bool:
    with chosen(kind):
        fast = corridor_clearance(points, headings, half_width_m=half_width_m, origins=origins)
    plain = ref_clearance(points, headings, half_width_m=half_width_m, origins=origins)
    return fast.tobytes() == plain.tobytes()


@both_paths
@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.builds(Vec2, st.floats(-3.0, 3.0), st.floats(-3.0, 3.0)), min_size=1, max_size=4),
    st.floats(0.05, 1.2),
    st.integers(0, 2**32 - 1),
)
def test_points_on_a_slots_corridor_edge_count_as_in_the_plain_pass(
    kind: str, others: list[Vec2], half_width_m: float, seed: int
) -> None:
    """Points a few units in the last place either side of a turned slot's corridor edge
    and of the line through its centre, along every heading: the fast path picks its
    candidates from rounded components, then decides each as the plain pass does.
    """
    rng = np.random.default_rng(seed)
    k = rng.integers(0, HEADINGS_RAD.size, 60)
    o = [others[i] for i in rng.integers(0, len(others), 60)]
    c, s = np.cos(HEADINGS_RAD[k]), np.sin(HEADINGS_RAD[k])
    ox = np.array([v.x_m for v in o])
    oy = np.array([v.y_m for v in o])
    along = np.where(rng.random(60) < 0.3, 0.0, rng.uniform(0.0, 4.0, 60))
    across = half_width_m * rng.choice([-1.0, 1.0, 0.0], 60)
    ulps = rng.integers(-4, 5, 60) * np.spacing(np.maximum(np.abs(across), 1.0))
    across, along = across + ulps, along + ulps[::-1]
    x = c * ox - s * oy + along * c - across * s
    y = s * ox + c * oy + along * s + across * c
    assert _same_as_plain(kind, (x, y), HEADINGS_RAD, half_width_m, [Vec2(0.0, 0.0), *others])


@both_paths
def test_points_not_all_finite_count_as_in_the_plain_pass(kind: str) -> None:
    """(Both passes multiply an infinity by a zero on the way: numpy says so.)"""
    x = np.array([1.0, np.nan, 2.0, np.inf, 0.5])
    y = np.array([0.1, 0.0, np.nan, 0.2, -0.3])
    slots = [Vec2(0.0, 0.0), Vec2(-0.8, 0.6), Vec2(-0.8, -0.6)]
    with np.errstate(invalid="ignore"):
        assert _same_as_plain(kind, (x, y), HEADINGS_RAD, 0.3, slots)
        assert _same_as_plain(kind, (x, y), HEADINGS_RAD, 0.3, slots[1:])


@both_paths
@settings(max_examples=100, deadline=None)
@given(echoes(), echoes(), st.floats(0.05, 1.2))
def test_the_projections_kept_are_never_those_of_other_points(
    kind: str, first: tuple[Floats, Floats], second: tuple[Floats, Floats], half_width_m: float
) -> None:
    """The same arrays written over in place between calls (x, then y; a copy of the
    first with the arrays it came from written over), then other widths and headings,
    the shape's slots among them: each call gives the plain pass of what it is given
    then."""
    x, y = first
    n = min(x.size, second[0].size)
    shape = [Vec2(0.0, 0.0), Vec2(-0.8, 0.6)]
    assert _same_as_plain(kind, (x, y), HEADINGS_RAD, half_width_m, shape)
    kept = (x.copy(), y.copy())
    x[:n] = second[0][:n]
    assert _same_as_plain(kind, kept, HEADINGS_RAD, half_width_m, shape)
    assert _same_as_plain(kind, (x, y), HEADINGS_RAD, half_width_m, shape)
    assert _same_as_plain(kind, (x, y), HEADINGS_RAD, half_width_m)
    y[:n] = second[1][:n]
    assert _same_as_plain(kind, (x, y), HEADINGS_RAD, half_width_m)
    assert _same_as_plain(kind, (x, y), HEADINGS_RAD, half_width_m * 1.5)
    assert _same_as_plain(kind, (x, y), SIDEWAYS_RAD, half_width_m)
