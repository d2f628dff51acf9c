"""An operator's commands on the wire and into a step: `OperatorCommand` in both forms,
bounded like every message (speeds within the fleet's rating, finite numbers, a twist or
a goal asked for), and the agent runtime's inbox that hands the agent the newest twist,
aged on the operator's own clock, and each goal once.
"""

from __future__ import annotations

import math

import pytest
from receivers import LoopbackSession

from phalanx.agents.inputs import OPERATOR_TIMEOUT_S
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.geometry import Twist2D, Vec2
from phalanx.runtime.operator import OperatorInbox
from phalanx.wire.bounds import FleetBounds
from phalanx.wire.codec import DecodeStats, decode, encode
from phalanx.wire.keys import robot_key
from phalanx.wire.messages import OperatorCommand

WEDGE = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
BOUNDS = FleetBounds.of(WEDGE, load_robot(WEDGE.robot))
TWIST = {"robot_id": "r1", "stamp_s": 1.8e9, "twist": True, "v_mps": 0.2, "omega_radps": -0.4}
GOAL = {"robot_id": "r1", "stamp_s": 1.8e9, "goal": True, "goal_x_m": 4.0, "goal_y_m": -2.0}


@pytest.mark.parametrize("fmt", ["packed", "json"])
@pytest.mark.parametrize("fields", [TWIST, GOAL, {**TWIST, **GOAL}])
def test_an_operator_command_round_trips(fmt: str, fields: dict[str, object]) -> None:
    command = OperatorCommand.model_validate(fields)
    assert decode(OperatorCommand, encode(command, fmt), context=BOUNDS) == command  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "changes",
    [
        {"twist": False},  # asks for nothing
        {"v_mps": 5.0},  # beyond the P3DX's rating (x 1.5)
        {"omega_radps": -20.0},
        {"v_mps": math.nan},
        {"goal": True, "goal_x_m": math.inf},
        {"goal": True, "goal_y_m": 1e7},  # out of any world
        {"robot_id": "r9"},  # not of this fleet
        {"stamp_s": -1.0},
    ],
)
def test_a_command_out_of_bounds_is_dropped_and_counted(changes: dict[str, object]) -> None:
    bad = OperatorCommand.model_construct(**{**OperatorCommand(**TWIST).model_dump(), **changes})  # type: ignore[arg-type]
    for fmt in ("packed", "json"):
        stats = DecodeStats()
        assert decode(OperatorCommand, encode(bad, fmt), stats, context=BOUNDS) is None  # type: ignore[arg-type]
        assert stats.malformed["OperatorCommand"] == 1


class Clock:
    """This machine's monotonic clock, moved by hand (s)."""

    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s


def _inbox() -> tuple[OperatorInbox, LoopbackSession, Clock]:
    clock = Clock()
    inbox = OperatorInbox("fleet", "r1", clock=clock)
    session = LoopbackSession()
    inbox.attach(session, BOUNDS)  # type: ignore[arg-type]
    return inbox, session, clock


def _send(session: LoopbackSession, **fields: object) -> None:
    session.inject(robot_key("fleet", "r1", "operator"), encode(OperatorCommand(**fields)))  # type: ignore[arg-type]


def test_the_agent_gets_the_newest_twist_aged_on_the_operators_clock() -> None:
    inbox, session, clock = _inbox()
    assert inbox.take(1.0) is None  # nothing from an operator yet
    _send(session, **TWIST)
    _send(session, **{**TWIST, "stamp_s": 1.8e9 + 0.1, "v_mps": 0.3})
    clock.now_s += 0.2
    given = inbox.take(5.0)
    assert given is not None
    assert given.twist == Twist2D(0.3, -0.4)
    assert given.stamp_s == pytest.approx(4.8)  # heard 0.2 s before the step
    assert given.goal is None
    assert given.drives(5.0)
    # It goes on being handed in, older at each step, and stops driving once it is
    # OPERATOR_TIMEOUT_S old, whatever the fleet's clock did meanwhile.
    clock.now_s += OPERATOR_TIMEOUT_S - 0.2 - 0.01
    later = inbox.take(7.0)
    assert later is not None
    assert later.drives(7.0)
    clock.now_s += 0.02
    stale = inbox.take(7.1)
    assert stale is not None
    assert not stale.drives(7.1)
    assert inbox.counters() == {"operator_commands": 2, "operator_goals": 0}


def test_a_goal_is_handed_on_once() -> None:
    inbox, session, _ = _inbox()
    _send(session, **GOAL)
    first = inbox.take(2.0)
    assert first is not None
    assert (first.goal, first.twist) == (Vec2(4.0, -2.0), None)
    assert inbox.take(2.1) is None
    _send(session, **{**TWIST, **GOAL, "stamp_s": 1.8e9 + 1.0})
    both = inbox.take(3.0)
    assert both is not None
    assert both.goal == Vec2(4.0, -2.0)
    assert both.twist == Twist2D(0.2, -0.4)
    again = inbox.take(3.1)
    assert again is not None
    assert again.goal is None  # the twist stays, the goal was given
    assert inbox.counters() == {"operator_commands": 2, "operator_goals": 2}


def test_a_command_on_another_robots_key_never_reaches_the_agent() -> None:
    inbox, session, _ = _inbox()
    session.inject(
        robot_key("fleet", "r1", "operator"), encode(OperatorCommand(**{**TWIST, "robot_id": "r2"}))
    )  # type: ignore[arg-type]
    assert inbox.take(1.0) is None
    assert session.stats.rejected["OperatorCommand"] == 1
