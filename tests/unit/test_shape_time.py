"""The bound on time in the scenario's shape a way allows (phalanx.analysis.shape_time)."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from phalanx.analysis.shape_time import kept_at_most, returns_s, stretches

DT_S = 0.1
series = st.lists(st.booleans(), max_size=200).map(lambda v: np.array(v, dtype=bool))
seconds = st.integers(min_value=0, max_value=30).map(lambda k: k * DT_S)


def test_stretches_are_the_runs_of_fitting_steps() -> None:
    fits = np.array([1, 1, 0, 0, 1, 0, 1, 1, 1], dtype=bool)
    assert stretches(fits) == [(0, 2), (4, 5), (6, 9)]
    assert stretches(np.zeros(3, dtype=bool)) == []


def test_a_group_back_in_the_shape_after_a_long_narrowing_only() -> None:
    # fits 0-9, a narrowing of 5 steps, fits 15-29, a narrowing of 1 step, fits 31-39
    fits = np.ones(40, dtype=bool)
    fits[10:15] = False
    fits[30] = False
    # back in 3 steps after a narrowing of 2 or more; the 1-step one ridden through
    assert kept_at_most(fits, DT_S, back_s=0.3, ride_s=0.2) == 10 + 12 + 9
    # a narrowing at the start counts as one
    assert kept_at_most(fits[12:], DT_S, back_s=0.3, ride_s=0.2) == 12 + 9


@given(series)
def test_an_instant_return_keeps_every_fitting_step(fits: np.ndarray) -> None:
    assert kept_at_most(fits, DT_S, back_s=0.0, ride_s=0.0) == int(fits.sum())


@given(series, seconds, seconds, seconds)
def test_the_bound_falls_with_the_return_and_rises_with_the_ride(
    fits: np.ndarray, back_s: float, more_s: float, ride_s: float
) -> None:
    kept = kept_at_most(fits, DT_S, back_s=back_s, ride_s=ride_s)
    assert 0 <= kept <= int(fits.sum())
    assert kept_at_most(fits, DT_S, back_s=back_s + more_s, ride_s=ride_s) <= kept
    assert kept_at_most(fits, DT_S, back_s=back_s, ride_s=ride_s + more_s) >= kept


def test_how_long_a_group_took_to_get_back_in_the_shape() -> None:
    fits = np.array([1, 1, 0, 0, 1, 1, 1, 1, 0, 1, 1], dtype=bool)
    in_shape = np.array([1, 1, 0, 0, 0, 0, 1, 1, 0, 0, 0], dtype=bool)
    # back 2 steps into the second stretch; never in the third; the first is the start
    assert returns_s(in_shape, fits, DT_S) == ([2 * DT_S], 1)
