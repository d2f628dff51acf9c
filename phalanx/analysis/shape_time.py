"""What the way a group took allowed of time in the scenario's shape.

A run records, per step, whether its leader's map showed the scenario's shape fitting
the way (`phalanx.analysis.metrics.scenario_shape_series`). The steps it fitted come in
stretches; between two, the way was narrower than the shape. A group that left the
shape in a narrowing is back in it some time after the way widens again: it slides its
robots back and settles. `kept_at_most` counts the fitting steps a group could be in
the shape at best, given how long it takes to get back in (`back_s`) and how short a
narrowing it could ride through whole (`ride_s`): an upper bound for any rule of when
to reshape, on the way that run took.
"""

from __future__ import annotations

import numpy as np

from phalanx.analysis.metrics import BoolArray


def stretches(fits: BoolArray) -> list[tuple[int, int]]:
    """The runs of True steps in `fits`: (first step, step after the last), in order."""
    edges = np.flatnonzero(np.diff(np.concatenate(([0], fits.astype(np.int8), [0]))))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def kept_at_most(fits: BoolArray, dt_s: float, *, back_s: float, ride_s: float) -> int:
    """How many of the steps `fits` marks a group could be in the scenario's shape: it
    starts in it, rides through whole every narrowing (a run of False steps) shorter
    than `ride_s`, and after a longer one is back in the shape `back_s` after the way
    widens (a narrowing at the start counts as one).
    """
    back, ride = round(back_s / dt_s), round(ride_s / dt_s)
    kept, ready, last_end = 0, 0, 0
    for start, end in stretches(fits):
        if start > 0 and start - last_end >= ride:
            ready = start + back
        kept += max(0, end - max(start, ready))
        last_end = end
    return kept


def returns_s(in_shape: BoolArray, fits: BoolArray, dt_s: float) -> tuple[list[float], int]:
    """How long after the way widened the group was back in the shape (s), over the
    stretches after a narrowing it was out of the shape at the start of; and how many
    of those it never got back in.
    """
    back: list[float] = []
    never = 0
    for start, end in stretches(fits):
        if start == 0 or in_shape[start]:
            continue
        inside = np.flatnonzero(in_shape[start:end])
        if inside.size:
            back.append(float(inside[0]) * dt_s)
        else:
            never += 1
    return back, never
