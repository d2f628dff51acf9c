"""Masking the formation out of the sonar: a batch of robots (the batch runner's one pass)
gives each robot, bit for bit, what masking that robot on its own gives (an agent in its
own process: the lockstep and real-time runtimes). The two take different code paths
(a robot alone has one robot's slot discs), and `phalanx up` must reproduce `phalanx run`.
Leaving out the slot discs no echo can reach (a large fleet's masking) changes nothing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from phalanx.agents import masking
from phalanx.agents.masking import MaskInputs, SlotMasks, mask_readings
from phalanx.agents.perception import MaskedEchoes, SonarGeometry
from phalanx.analysis.sweep import Job
from phalanx.runtime.batch import BatchRunner

STEPS = 120
EVERY = 8  # steps between two captured passes


@dataclass(frozen=True)
class Pass:
    """One step's masking as the batch runner did it, and each robot's own slot masks."""

    sonar: SonarGeometry
    ranges_m: np.ndarray
    inputs: tuple[MaskInputs, ...]
    fleet: SlotMasks
    own: tuple[SlotMasks, ...]


@pytest.fixture(scope="module")
def passes() -> list[Pass]:
    """Every `EVERY`-th step's masking of a wedge of five in an obstacle field."""
    runner = BatchRunner(Job("field", "wedge", 5, 3).scenario())
    seen: list[Pass] = []

    def spy(sonar: SonarGeometry, readings: Sequence[Any], inputs: Any, slots: SlotMasks) -> Any:
        if runner.done % EVERY == 0:
            own = tuple(agent.slot_masks for agent in runner.agents.values())
            ranges = np.stack([rd.ranges_m for rd in readings])
            seen.append(Pass(sonar, ranges, tuple(inputs), slots, own))
        return mask_readings(sonar, readings, inputs, slots)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("phalanx.runtime.batch.mask_readings", spy)
        runner.run(until=lambda b: b.done >= STEPS)
    return seen


def _disc_ranges(sonar: SonarGeometry, step: Pass) -> list[float]:
    """Ranges at which a transducer's echo lies about the edge of a slot disc or the
    tracked robot's (the nearest and furthest points of each from each transducer).
    """
    ranges = set()
    discs = [
        (float(x), float(y), step.fleet.slot_radius_m)
        for x, y in zip(step.fleet.cx.ravel(), step.fleet.cy.ravel(), strict=True)
    ]
    for heard in step.inputs:  # the tracked robot where its state puts it, near enough
        if heard.view.lead is not None:
            there = heard.pose.to_body(heard.view.lead.pose.position)
            discs.append((there.x_m, there.y_m, step.fleet.tracked_radius_m))
    for cx, cy, radius in discs:
        d = np.hypot(cx - sonar.unit_x_m, cy - sonar.unit_y_m)
        ranges.update((d - radius).tolist() + (d + radius).tolist())
    return sorted(r for r in ranges if 0.0 <= r <= sonar.max_range_m)


def _same(a: MaskedEchoes, b: MaskedEchoes) -> None:
    assert a.robot_id == b.robot_id
    assert np.array_equal(a.echo, b.echo)
    assert np.array_equal(a.points[0], b.points[0])
    assert np.array_equal(a.points[1], b.points[1])
    assert (a.ahead_m, a.behind_m) == (b.ahead_m, b.behind_m)


def _ranges(step: Pass, data: st.DataObject) -> np.ndarray:
    """The pass's ranges, each transducer keeping the range the world gave it or taking
    any other one: echoes anywhere, near the slot discs and the tracked robot's disc
    among them.
    """
    sonar = step.sonar
    shape = step.ranges_m.shape
    top = sonar.max_range_m
    near_a_disc = st.builds(
        lambda d, e: min(top, max(0.0, d + e)),
        st.sampled_from(_disc_ranges(sonar, step)),
        st.floats(-0.02, 0.02),
    )
    redrawn = data.draw(arrays(np.bool_, shape))
    drawn = data.draw(arrays(np.float64, shape, elements=st.floats(0.0, top) | near_a_disc))
    return np.where(redrawn, drawn, step.ranges_m)


@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_leaving_out_the_discs_no_echo_reaches_changes_no_mask(
    passes: list[Pass], data: st.DataObject
) -> None:
    step = data.draw(st.sampled_from(passes))
    sonar = step.sonar
    ranges = _ranges(step, data)
    readings = sonar.read_all(ranges).readings
    reached = step.fleet.reached(sonar, ranges, ranges < sonar.max_range_m - 1e-6)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(masking, "REACH_FROM_DISCS", 0)  # every pass leaves them out
        left_out = mask_readings(sonar, readings, step.inputs, step.fleet)
        patch.setattr(masking, "REACH_FROM_DISCS", 10**9)  # none does
        kept = mask_readings(sonar, readings, step.inputs, step.fleet)
    for a, b in zip(left_out, kept, strict=True):
        _same(a, b)
    # and no disc an echo's arc meets is among those left out
    echo = ranges < sonar.max_range_m - 1e-6
    for k in np.flatnonzero(~reached):
        i = step.fleet.owner[k]
        cx, cy = step.fleet.cx[k : k + 1], step.fleet.cy[k : k + 1]
        dirs = (step.fleet.cos[k : k + 1], step.fleet.sin[k : k + 1])
        met = sonar.arcs_meet_at(ranges[i : i + 1], cx, cy, step.fleet.slot_radius_m, dirs)
        assert not (met[0] & echo[i]).any()


@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_a_batch_masks_each_robot_as_masking_it_alone_does(
    passes: list[Pass], data: st.DataObject
) -> None:
    assert len(passes) >= STEPS // EVERY - 1  # the spy saw the runner's passes
    assert any(heard.view.lead is not None for p in passes for heard in p.inputs)
    step = data.draw(st.sampled_from(passes))
    sonar = step.sonar
    ranges = _ranges(step, data)
    together = mask_readings(sonar, sonar.read_all(ranges).readings, step.inputs, step.fleet)
    for i, (inputs, own) in enumerate(zip(step.inputs, step.own, strict=True)):
        alone = mask_readings(sonar, [sonar.read(ranges[i])], [inputs], own)
        _same(together[i], alone[0])


@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_readings_without_an_echo_are_masked_as_the_arithmetic_masks_them(
    passes: list[Pass], data: st.DataObject
) -> None:
    """Open space (every range at the ring's maximum or beyond): masking takes a short
    way round its arithmetic, alone and in a batch, and gives what the arithmetic gives.
    """
    step = data.draw(st.sampled_from(passes))
    sonar, shape = step.sonar, step.ranges_m.shape
    top = sonar.max_range_m
    quiet = st.floats(top - 1e-6, top + 5.0) | st.just(top)
    ranges = data.draw(arrays(np.float64, shape, elements=quiet))
    batch = sonar.read_all(ranges)
    assert not batch.echo.any()
    together = mask_readings(sonar, batch.readings, step.inputs, step.fleet)
    worked_out = masking._masked(sonar, batch, step.inputs, step.fleet)
    for i, (inputs, own) in enumerate(zip(step.inputs, step.own, strict=True)):
        _same(together[i], worked_out[i])
        reading = sonar.read(ranges[i])
        alone = mask_readings(sonar, [reading], [inputs], own)[0]
        _same(alone, masking._masked(sonar, masking._batch_of([reading]), [inputs], own)[0])
        assert (alone.t_s, alone.points[0].dtype) == (inputs.t_s, worked_out[i].points[0].dtype)
