"""Numbers on the command line are checked as a file's are: a time, a speed factor or a
port out of range, NaN included, is refused while the options are read (exit 2, the
option named), before anything starts. Each case below once ran: `up --timeout -5`
reported a run "timed out after -5 s", `up --speed 1e300` ran the world for no tick,
`emulate --tcp 99999` ended in an OverflowError's traceback, `emulate --watchdog nan`
served a robot whose firmware watchdog never fired, `sweep --robots 100000` printed
pydantic's raw error with a link to its docs.
"""

from __future__ import annotations

import math

import pytest
import typer
from typer.testing import CliRunner

from phalanx.cli import app
from phalanx.cli.numbers import seconds, seconds_or_ever, speed_factor
from phalanx.core.config_files import CONFIG_ROOT

WEDGE = str(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
DEPLOYMENT = str(CONFIG_ROOT / "deployments" / "amrisim.toml")

# argv, the option the message names
CASES: dict[str, tuple[list[str], str]] = {
    "up, a negative timeout": (["up", WEDGE, "--timeout", "-5"], "--timeout"),
    "up, no timeout at all": (["up", WEDGE, "--timeout", "nan"], "--timeout"),
    "up, faster than fast": (["up", WEDGE, "--speed", "1e300"], "--speed"),
    "up, a speed of nan": (["up", WEDGE, "--speed", "nan"], "--speed"),
    "world, standing still": (["world", WEDGE, "--speed", "0"], "--speed"),
    "emulate, a port past 65535": (["emulate", "--tcp", "99999"], "--tcp"),
    "emulate, a watchdog of nan": (["emulate", "--tcp", "0", "--watchdog", "nan"], "--watchdog"),
    "view, a port past 65535": (["view", "--port", "99999"], "--port"),
    "mocap, a duration of nan": (["mocap", WEDGE, "--duration", "nan"], "--duration"),
    "ros2, a negative duration": (["ros2", WEDGE, "--duration", "-1"], "--duration"),
    "launch, a timeout of nan": (["launch", DEPLOYMENT, "--timeout", "nan"], "--timeout"),
    "status, listening for ever": (["status", DEPLOYMENT, "--listen-s", "1e300"], "--listen-s"),
    "stop, a wait of nan": (["stop", DEPLOYMENT, "--wait", "nan"], "--wait"),
    "stop, a negative host wait": (["stop", DEPLOYMENT, "--host-wait", "-1"], "--host-wait"),
    "sweep, a group of 100 000": (["sweep", "--robots", "3", "--robots", "100000"], "--robots"),
    "sweep, a group of none": (["sweep", "--robots", "0"], "--robots"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_number_out_of_range_is_refused_with_the_option_named(case: str) -> None:
    argv, option = CASES[case]
    result = CliRunner().invoke(app, argv, prog_name="phalanx")
    assert result.exit_code == 2, result.output
    assert f"Invalid value for '{option}'" in result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)


@pytest.mark.parametrize("value", [0.0, 0.5, 86_400.0])
def test_a_time_within_a_day_is_taken_as_it_is(value: float) -> None:
    assert seconds(value) == value
    assert seconds(None) is None
    assert seconds_or_ever(value) == value
    assert seconds_or_ever(math.inf) == math.inf


@pytest.mark.parametrize("value", [-1e-9, 86_400.5, math.inf, -math.inf, math.nan])
def test_a_time_past_a_day_or_not_a_number_is_refused(value: float) -> None:
    with pytest.raises(typer.BadParameter):
        seconds(value)
    if value != math.inf:
        with pytest.raises(typer.BadParameter):
            seconds_or_ever(value)


@pytest.mark.parametrize("value", [0.0, 0.009, 1000.5, math.inf, math.nan])
def test_a_speed_factor_out_of_range_is_refused(value: float) -> None:
    with pytest.raises(typer.BadParameter):
        speed_factor(value)
    assert speed_factor(0.01) == 0.01
    assert speed_factor(1000.0) == 1000.0
