"""Formation reconfiguration: the shapes, the planned slides between them (no robot
crosses another's path), the shape key on the wire."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from phalanx.core.formation import resolve_formation
from phalanx.core.peers import PeerState
from phalanx.core.scenarios import SHAPES, formation_shape
from phalanx.core.shapes import (
    COLUMN,
    RAMP_SHARE,
    SCENARIO_SHAPE,
    SHRUNK,
    ShapeBook,
    ShapeKey,
    slide_share,
)
from phalanx.wire.codec import decode, encode
from phalanx.wire.messages import RobotFlags, RobotState

ROBOT_RADIUS_M = 0.25


def _book(shape: str, n: int) -> ShapeBook:
    return ShapeBook(resolve_formation(formation_shape(shape, n)))  # type: ignore[arg-type]


@pytest.mark.parametrize("n", [3, 5])
@pytest.mark.parametrize("shape", SHAPES)
def test_slides_between_any_two_shapes_never_bring_two_robots_together(shape: str, n: int) -> None:
    book = _book(shape, n)
    for a, b in itertools.permutations((SCENARIO_SHAPE, SHRUNK, COLUMN), 2):
        closest = np.inf
        for morph in np.linspace(0.0, 1.0, 201):
            slots = list(book.positions(ShapeKey(a, b, float(morph))).values())
            gaps = [(p - q).norm() for p, q in itertools.combinations(slots, 2)]
            closest = min(closest, *gaps)
        assert closest >= 2 * ROBOT_RADIUS_M, (shape, n, a, b, closest)


@pytest.mark.parametrize("shape", SHAPES)
def test_the_leader_keeps_its_slot_and_the_column_is_a_line(shape: str) -> None:
    book = _book(shape, 5)
    column = book.shapes[COLUMN]
    assert column["r1"].norm() == 0.0
    assert sorted(round(p.x_m, 9) for p in column.values()) == [-4.0, -3.0, -2.0, -1.0, 0.0]
    assert all(p.y_m == 0.0 for p in column.values())
    assert book.half_span_m(COLUMN, ROBOT_RADIUS_M) < book.half_span_m(SHRUNK, 0.25) or (
        shape == "inline"
    )


def test_a_wedge_folds_robots_into_the_nearest_column_slots() -> None:
    book = _book("wedge", 5)
    column = book.shapes[COLUMN]
    # the two robots nearest the leader take the two column slots nearest it
    assert {round(-column[r].x_m) for r in ("r2", "r3")} == {1, 2}
    assert {round(-column[r].x_m) for r in ("r4", "r5")} == {3, 4}


def test_the_shape_in_effect_goes_out_in_the_state_and_the_flags() -> None:
    state = PeerState("r1", 3, 1.0, 0.0, 0.0, 0.0, 0.1, 0.0, "RESHAPE",
                      shape_source=0, shape_target=2, morph=0.25)  # fmt: skip
    message = RobotState.of(state)
    back = decode(RobotState, encode(message))
    assert back is not None
    assert (back.shape_source, back.shape_target, back.morph) == (0, 2, 0.25)
    flags = decode(RobotFlags, encode(message.flags()))
    assert flags is not None
    assert (flags.shape_target, flags.morph) == (2, 0.25)


def test_an_unknown_shape_or_a_morph_out_of_range_is_refused() -> None:
    good = RobotState.of(PeerState("r1", 3, 1.0, 0.0, 0.0, 0.0, 0.1, 0.0, "NAVIGATE"))
    assert decode(RobotState, encode(good.model_copy(update={"shape_target": 7}))) is None
    assert decode(RobotState, encode(good.model_copy(update={"morph": 1.5}))) is None


@given(st.floats(-0.5, 1.5), st.floats(1e-6, 0.5))
def test_a_slide_starts_and_stops_gently_and_is_never_faster_than_its_peak(
    s: float, ds: float
) -> None:
    """`slide_share`: 0 before the slide, 1 after it, half-way at half time, never going
    back, and never covering more of the way in a time than its peak pace, 1 / (1 -
    `RAMP_SHARE`) times the mean (that is what `RESHAPE_PEAK_MPS` bounds).
    """
    assert slide_share(min(s, 0.0)) == 0.0
    assert slide_share(max(s, 1.0)) == 1.0
    assert slide_share(0.5) == pytest.approx(0.5)
    gained = slide_share(s + ds) - slide_share(s)
    assert -1e-12 <= gained <= ds / (1 - RAMP_SHARE) + 1e-12
    # gently: behind the mean pace through the first ramp, and the end the start reversed
    start = min(max(s, 0.0), RAMP_SHARE)
    assert slide_share(start) <= start
    assert slide_share(1.0 - start) == pytest.approx(1.0 - slide_share(start))
