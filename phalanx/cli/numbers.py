"""Numbers given on the command line, checked as a file's are (`phalanx.core.quantities`):
typer callbacks for options whose range click cannot state. Click's ranges let NaN
through (it compares false with either end), and a time has no upper end there.
"""

from __future__ import annotations

import math

import typer

# A real-time run may go this many times faster than the wall clock, at most (a
# deployment's `[world] speed` has the same bound).
MAX_SPEED_FACTOR = 1000.0
# TCP and UDP ports (0: one the system picks, where a command says so).
PORT_MAX = 65535


def finite_epoch(value: float | None) -> float | None:
    """An `--epoch`, if given, is a Unix time: a number, not nan or inf."""
    if value is not None and not math.isfinite(value):
        raise typer.BadParameter(f"{value} is not a Unix time")
    return value


def seconds(value: float | None) -> float | None:
    """A time in seconds, if given: 0 to a day."""
    from phalanx.core.quantities import MAX_DURATION_S  # (pydantic's: not for `--help`)

    if value is not None and not 0.0 <= value <= MAX_DURATION_S:
        raise typer.BadParameter(f"{value} is not a time from 0 to {MAX_DURATION_S:g} s")
    return value


def seconds_or_ever(value: float) -> float:
    """A time in seconds (`seconds`), or inf: for as long as it takes."""
    if value != math.inf:
        seconds(value)
    return value


def speed_factor(value: float) -> float:
    """How many times faster than the wall clock: 0.01 to `MAX_SPEED_FACTOR`."""
    if not 0.01 <= value <= MAX_SPEED_FACTOR:
        raise typer.BadParameter(f"{value} is not a speed factor from 0.01 to {MAX_SPEED_FACTOR:g}")
    return value


def group_sizes(values: list[int] | None) -> list[int] | None:
    """Group sizes, if given: each 1 to the most robots a scenario may have."""
    from phalanx.core.config import MAX_ROBOTS  # (pydantic's: not for `--help`)

    for value in values or ():
        if not 1 <= value <= MAX_ROBOTS:
            raise typer.BadParameter(f"{value} is not a group size from 1 to {MAX_ROBOTS}")
    return values
