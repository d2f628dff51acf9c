"""`QuantisedHeading`: a heading a simulator reports in whole degrees (AMRISim), followed
finer from the yaw rate it reports with it. Whatever the rates, the estimate stays in the
step the report allows; turning at a steady rate, once it has crossed a step's edge it is
within half an interval's turn of the truth, where the whole degree alone is within 0.5."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from phalanx.core.geometry import wrap_angle
from phalanx.drivers.arcos_tracker import CHORD_EASE_S, QuantisedHeading

STEP = math.radians(1.0)
intervals = st.lists(st.floats(0.05, 0.15), min_size=5, max_size=80)


def _reported(heading: float) -> float:
    """What AMRISim sends: the heading rounded to a whole step, wrapped."""
    return wrap_angle(round(wrap_angle(heading) / STEP) * STEP)


def _error(a: float, b: float) -> float:
    return abs(wrap_angle(a - b))


@given(
    start=st.floats(-math.pi, math.pi),
    rate=st.floats(-math.radians(20.0), math.radians(20.0)),
    dts=intervals,
)
def test_turning_steadily_it_is_within_half_an_intervals_turn(
    start: float, rate: float, dts: list[float]
) -> None:
    follower = QuantisedHeading(STEP)
    t, heading, crossed = 0.0, start, False
    first = _reported(heading)
    follower.update(first, rate, t)
    for dt in dts:
        t, heading = t + dt, heading + rate * dt
        got = follower.update(_reported(heading), rate, t)
        assert _error(got, _reported(heading)) <= STEP / 2 + 1e-9  # in the reported step
        crossed = crossed or _reported(heading) != first
        if crossed:
            assert _error(got, heading) <= abs(rate) * max(dts) / 2 + 1e-9
        else:
            assert _error(got, heading) <= STEP / 2 + 1e-9


@given(
    start=st.floats(-math.pi, math.pi),
    steps=st.lists(
        st.tuples(st.floats(0.05, 0.15), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0)),
        min_size=1,
        max_size=60,
    ),
)
def test_whatever_the_rates_it_stays_in_the_reported_step(
    start: float, steps: list[tuple[float, float, float]]
) -> None:
    """The true rate and the one reported may disagree (odometry errors, a rate rounded
    to whole degrees): the report still bounds the estimate."""
    follower = QuantisedHeading(STEP)
    t, heading = 0.0, start
    follower.update(_reported(heading), 0.0, t)
    for dt, true_rate, told_rate in steps:
        t, heading = t + dt, heading + true_rate * dt
        got = follower.update(_reported(heading), told_rate, t)
        assert _error(got, _reported(heading)) <= STEP / 2 + 1e-9


@given(
    start=st.floats(-math.pi, math.pi),
    way=st.sampled_from((1, -1)),
    speed=st.floats(0.05, 0.5),
    rate=st.floats(-math.radians(2.0), math.radians(2.0)),
)
def test_driving_on_a_chord_puts_the_heading_on_its_direction(
    start: float, way: int, speed: float, rate: float
) -> None:
    """A long reverse in a straight line crosses no edge: the heading stays wherever the
    last crossing left it, and an error of 0.3 deg walks the robot 2 cm aside over 4 m.
    Positions in half millimetres set it right from the chord."""
    follower = QuantisedHeading(STEP)
    t, x, y, heading = 0.0, 0.0, 0.0, start
    for _ in range(300):  # 30 s
        dt = 0.1
        t += dt
        heading += rate * dt
        x += way * speed * dt * math.cos(heading - 0.5 * rate * dt)
        y += way * speed * dt * math.sin(heading - 0.5 * rate * dt)
        seen = (round(x * 2000) / 2000, round(y * 2000) / 2000)
        got = follower.update(_reported(heading), rate, t, position=seen, way=way)
    assert _error(got, heading) < math.radians(0.1)


@given(
    start=st.floats(-math.pi, math.pi),
    way=st.sampled_from((1, -1)),
    speed=st.floats(0.05, 0.5),
)
def test_a_chords_correction_is_eased_in_not_jumped(start: float, way: int, speed: float) -> None:
    """Driving straight, the estimate starts up to half a step off and the chords set it
    right: a little every report (a heading that jumps moves every slot behind the robot
    sideways at once), and all of it within a few CHORD_EASE_S."""
    follower = QuantisedHeading(STEP)
    t, x, y, dt = 0.0, 0.0, 0.0, 0.1
    last = follower.update(_reported(start), 0.0, t, position=(x, y), way=way)
    for _ in range(300):  # 30 s
        t += dt
        x += way * speed * dt * math.cos(start)
        y += way * speed * dt * math.sin(start)
        seen = (round(x * 2000) / 2000, round(y * 2000) / 2000)
        got = follower.update(_reported(start), 0.0, t, position=seen, way=way)
        # off by at most half a step, the chord within 0.1 deg: a tenth of that a report
        assert _error(got, last) <= (STEP / 2 + math.radians(0.1)) * dt / CHORD_EASE_S
        last = got
    assert _error(got, start) < math.radians(0.1)
