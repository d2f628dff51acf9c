"""`corridor_clearance`'s fast path gives what the plain pass over every (slot, heading,
point) gave, bit for bit, and its memory of the robot's own pass never outlives the
points it was worked out for. The plain pass is kept here, as it was, as the reference.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
from hypothesis import given, settings
from hypothesis import strategies as st

from phalanx.agents.navigation import HEADINGS_RAD, corridor_clearance
from phalanx.agents.perception import NO_OBSTACLE_M
from phalanx.core.geometry import Vec2

Floats = npt.NDArray[np.float64]
SIDEWAYS_RAD = np.array([np.pi / 2, -np.pi / 2])


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


@settings(max_examples=300, deadline=None)
@given(echoes(), slots, st.floats(0.05, 1.2), st.booleans(), st.booleans())
def test_clearances_are_the_plain_passes_to_the_bit(
    points: tuple[Floats, Floats],
    others: list[Vec2],
    half_width_m: float,
    turning: bool,
    sideways: bool,
) -> None:
    headings = SIDEWAYS_RAD if sideways else HEADINGS_RAD
    origins = [Vec2(0.0, 0.0), *others]
    for where in ((Vec2(0.0, 0.0),), origins, others):
        fast = corridor_clearance(
            points, headings, half_width_m=half_width_m, origins=where, turning=turning
        )
        plain = ref_clearance(
            points, headings, half_width_m=half_width_m, origins=where, turning=turning
        )
        assert fast.tobytes() == plain.tobytes()


def _same_as_plain(points: tuple[Floats, Floats], headings: Floats, half_width_m: float) -> bool:
    fast = corridor_clearance(points, headings, half_width_m=half_width_m)
    return fast.tobytes() == ref_clearance(points, headings, half_width_m=half_width_m).tobytes()


@settings(max_examples=100, deadline=None)
@given(echoes(), echoes(), st.floats(0.05, 1.2))
def test_the_own_pass_kept_is_never_that_of_other_points(
    first: tuple[Floats, Floats], second: tuple[Floats, Floats], half_width_m: float
) -> None:
    """The same arrays written over in place between calls (x, then y), then other
    widths and headings: each call gives the plain pass of what it is given then."""
    x, y = first
    n = min(x.size, second[0].size)
    assert _same_as_plain((x, y), HEADINGS_RAD, half_width_m)
    x[:n] = second[0][:n]
    assert _same_as_plain((x, y), HEADINGS_RAD, half_width_m)
    y[:n] = second[1][:n]
    assert _same_as_plain((x, y), HEADINGS_RAD, half_width_m)
    assert _same_as_plain((x, y), HEADINGS_RAD, half_width_m * 1.5)
    assert _same_as_plain((x, y), SIDEWAYS_RAD, half_width_m)
