"""The behaviour state machine: the generic machine, and every transition of the stack
pinned by a context that fires it (a transition added without a case here fails)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import pytest

from phalanx.agents.behaviours.stack import (
    ARBITRATION,
    STATE_NOTES,
    StackContext,
    behaviour_machine,
    behaviour_transitions,
)
from phalanx.agents.fsm import ANY_STATE, StateMachine, Transition, to_mermaid
from phalanx.agents.navigation import ScriptedProfile
from phalanx.core.config import LeaderProfile, Segment
from phalanx.core.states import State

S = State


@dataclass
class Ctx:
    x: int = 0


def test_priority_entry_exit_and_log() -> None:
    calls: list[str] = []
    fsm: StateMachine[Ctx] = StateMachine(
        initial="A",
        transitions=[
            Transition("A", "B", lambda c: c.x > 0, "x positive"),
            Transition("A", "C", lambda c: c.x > 5, "x large", priority=5),
            Transition(ANY_STATE, "A", lambda c: c.x < 0, "reset", priority=9),
        ],
        on_entry={"C": lambda c: calls.append("enter C")},
        on_exit={"A": lambda c: calls.append("exit A")},
    )
    assert fsm.update(Ctx(0), 0.0) is None
    event = fsm.update(Ctx(7), 1.0)
    assert event is not None
    assert (event.source, event.target, event.reason) == ("A", "C", "x large")
    assert calls == ["exit A", "enter C"]
    assert fsm.update(Ctx(-1), 2.0) is not None
    assert fsm.state == "A"
    assert fsm.update(Ctx(-1), 3.0) is None  # "*" never re-enters the state it is in
    assert [e.t_s for e in fsm.log] == [1.0, 2.0]
    assert fsm.states == ("A", "B", "C")


def test_absorbing_state_is_never_left_and_details_reach_the_log() -> None:
    fsm: StateMachine[Ctx] = StateMachine(
        initial="A",
        transitions=[
            Transition("A", "END", lambda c: c.x == 1, "done", detail=lambda c: f"x={c.x}"),
            Transition(ANY_STATE, "A", lambda c: True, "always"),
        ],
        absorbing=frozenset({"END"}),
    )
    event = fsm.update(Ctx(1), 0.0)
    assert event is not None
    assert event.reason == "done: x=1"
    assert fsm.update(Ctx(1), 1.0) is None
    assert fsm.state == "END"


def test_profile_segments_and_end() -> None:
    profile = ScriptedProfile(
        LeaderProfile(
            segments=(
                Segment(duration_s=2.0, v_mps=0.1),
                Segment(duration_s=1.0, v_mps=0.2, omega_degps=90.0),
            )
        )
    )
    assert profile.twist_at(1.0).v_mps == 0.1
    assert profile.twist_at(2.5).omega_radps > 1.5
    assert profile.twist_at(3.5).v_mps == 0.0


# --- every transition of the behaviour stack ---------------------------------------------

FOLLOWER = StackContext(is_leader=False, plan="goto", parent_fresh=True)
LEADER = StackContext(is_leader=True, plan="goto")
LEADS: dict[str, dict[str, Any]] = {
    S.NAVIGATE: {"is_leader": True, "plan": "goto"},
    S.WANDER: {"is_leader": True, "plan": "wander"},
    S.ARRIVED: {"is_leader": True, "arrived": True},
}


def _took(source: str) -> list[tuple[str, str, str, StackContext]]:
    return [
        (source, target, "took the lead", replace(FOLLOWER, **kw)) for target, kw in LEADS.items()
    ]


def _plan(source: str, reason: str, **extra: Any) -> list[tuple[str, str, str, StackContext]]:
    return [
        (source, target, reason, replace(LEADER, **{**kw, **extra})) for target, kw in LEADS.items()
    ]


ROBOT = (S.ESTOPPED, S.FAULT, S.STALLED, S.LOW_BATTERY)

CASES: list[tuple[str, str, str, StackContext]] = [
    # the robot's own conditions, and back once they clear
    (ANY_STATE, S.ESTOPPED, "the robot's emergency stop", replace(FOLLOWER, estopped=True)),
    (ANY_STATE, S.FAULT, "the robot reports a fault: left drive in FAULT",
     replace(FOLLOWER, faults=("left drive in FAULT",))),
    (ANY_STATE, S.STALLED, "a wheel is stalled", replace(FOLLOWER, stalled=True)),
    (ANY_STATE, S.LOW_BATTERY, "the battery is low: 10.8 V",
     replace(FOLLOWER, battery_low=True, battery_v=10.8)),
    *[(s, S.FORMATION_TRACK, "the robot is fine again: back to the formation", FOLLOWER)
      for s in ROBOT],
    *[case for s in ROBOT for case in _plan(s, "the robot is fine again: back to the plan")],
    # safety and shared
    (ANY_STATE, S.EMERGENCY_STOP, "bumper", replace(FOLLOWER, imminent=True)),
    (ANY_STATE, S.STUCK, "the formation leader is STUCK", replace(FOLLOWER, leader_state=S.STUCK)),
    (S.EMERGENCY_STOP, S.AVOID, "came to a standstill, way ahead blocked",
     replace(FOLLOWER, blocked_s=0.1)),
    (S.EMERGENCY_STOP, S.FORMATION_TRACK, "came to a standstill, way clear", FOLLOWER),
    *_plan(S.EMERGENCY_STOP, "came to a standstill, way clear: back to the plan"),
    (S.EMERGENCY_STOP, S.DEADLOCK_REVERSE, "deadlock", replace(LEADER, deadlock=True)),
    (S.EMERGENCY_STOP, S.STUCK, "deadlock and no retries left",
     replace(LEADER, deadlock=True, retries_left=False)),
    # leadership
    *_took(S.FORMATION_TRACK),
    *_took(S.FORMATION_REVERSE),
    *_took(S.AVOID),
    *_took(S.HOLD),
    *[(s, S.FORMATION_TRACK, "handed the lead on", FOLLOWER)
      for s in (S.NAVIGATE, S.WANDER, S.ARRIVED, S.DEADLOCK_REVERSE, S.DEADLOCK_TURN,
                S.RESHAPE, S.TELEOP)],
    *[(S.JOIN, t, "joined the fleet", replace(FOLLOWER, **kw)) for t, kw in LEADS.items()],
    (S.JOIN, S.FORMATION_TRACK, "joined the fleet", FOLLOWER),
    # formation layer
    *[(s, S.HOLD, "leader or tracked robot missing", replace(FOLLOWER, leader_lost=True))
      for s in (S.FORMATION_TRACK, S.FORMATION_REVERSE, S.AVOID)],
    (S.HOLD, S.FORMATION_REVERSE, "leader heard again, moving backwards",
     replace(FOLLOWER, parent_direction=-1)),
    (S.HOLD, S.FORMATION_TRACK, "leader heard again", FOLLOWER),
    (S.FORMATION_TRACK, S.FORMATION_REVERSE, "tracked robot moves backwards",
     replace(FOLLOWER, parent_v_mps=-0.1)),
    (S.FORMATION_REVERSE, S.FORMATION_TRACK, "tracked robot moves forwards",
     replace(FOLLOWER, parent_v_mps=0.1)),
    (S.FORMATION_TRACK, S.AVOID, "own path blocked while the leader's is clear",
     replace(FOLLOWER, blocked_s=0.3)),
    (S.AVOID, S.FORMATION_REVERSE, "the group reverses", replace(FOLLOWER, parent_v_mps=-0.1)),
    (S.AVOID, S.FORMATION_TRACK, "way back to the slot is free", replace(FOLLOWER, way_free_s=0.3)),
    # navigation layer
    (S.NAVIGATE, S.ARRIVED, "last waypoint reached", replace(LEADER, arrived=True)),
    *[(s, S.DEADLOCK_REVERSE, "deadlock", replace(LEADER, deadlock=True))
      for s in (S.NAVIGATE, S.WANDER)],
    *[(s, S.STUCK, "deadlock and no retries left",
       replace(LEADER, deadlock=True, retries_left=False)) for s in (S.NAVIGATE, S.WANDER)],
    (S.DEADLOCK_REVERSE, S.NAVIGATE, "backed off: the script resumes",
     replace(LEADER, plan="scripted", reversed_m=2.0)),
    (S.DEADLOCK_REVERSE, S.DEADLOCK_TURN, "obstacle behind", replace(LEADER, someone_stopped=True)),
    (S.DEADLOCK_REVERSE, S.DEADLOCK_TURN, "backed off the safe distance",
     replace(LEADER, path_used_up=True)),
    *_plan(S.DEADLOCK_TURN, "turned away", turned=True),
    (S.NAVIGATE, S.RESHAPE, "the way ahead needs another shape",
     replace(LEADER, plan="goto", reshape_wanted=True)),
    *[c for c in _plan(S.RESHAPE, "reshaped", reshaped=True) if c[1] != S.ARRIVED],
    # at the goal mid-slide (or settled, or not): it arrives, the slide ends standing
    *[(S.RESHAPE, S.ARRIVED, "last waypoint reached", replace(LEADER, arrived=True, reshaped=r))
      for r in (False, True)],
    (S.ARRIVED, S.NAVIGATE, "a new goal", LEADER),
    # an operator drives the leader, and hands it back to its plan when it stops
    *[(s, S.TELEOP, "an operator drives the leader", replace(LEADER, operator=True, **kw))
      for s, kw in ((S.NAVIGATE, {}), (S.WANDER, {"plan": "wander"}),
                    (S.ARRIVED, {"arrived": True}), (S.DEADLOCK_REVERSE, {}),
                    (S.DEADLOCK_TURN, {}))],
    (S.EMERGENCY_STOP, S.TELEOP, "came to a standstill, an operator drives the leader a clear",
     replace(LEADER, operator=True, way_clear=False)),
    *_plan(S.TELEOP, "the operator's commands stopped: back to the plan"),
]  # fmt: skip


def _initial(source: str) -> str:
    return S.FORMATION_TRACK if source == ANY_STATE else source


@pytest.mark.parametrize(
    ("source", "target", "reason", "ctx"),
    CASES,
    ids=[f"{c[0]}->{c[1]}:{c[2][:20]}" for c in CASES],
)
def test_transition_fires(source: str, target: str, reason: str, ctx: StackContext) -> None:
    fsm = behaviour_machine(_initial(source))
    event = fsm.update(ctx, 1.0)
    assert event is not None, f"nothing fired from {source}"
    assert (event.source, event.target) == (_initial(source), target)
    assert event.reason.startswith(reason), event.reason


def test_every_transition_has_a_case() -> None:
    pinned = {(source, target, reason.split(":")[0]) for source, target, reason, _ in CASES}
    for tr in behaviour_transitions():
        key = (tr.source, tr.target)
        assert any((s, t) == key and tr.reason.startswith(r) for s, t, r in pinned), (
            f"no test pins {tr.source} -> {tr.target} ({tr.reason})"
        )


def test_stuck_is_absorbing() -> None:
    fsm = behaviour_machine(S.STUCK)
    for ctx in (replace(LEADER, imminent=True), replace(FOLLOWER, parent_v_mps=-1.0)):
        assert fsm.update(ctx, 1.0) is None


def test_emergency_stop_outranks_avoidance_and_formation() -> None:
    fsm = behaviour_machine(S.FORMATION_TRACK)
    ctx = replace(FOLLOWER, imminent=True, blocked_s=1.0, parent_v_mps=-0.2)
    event = fsm.update(ctx, 0.0)
    assert event is not None
    assert event.target == S.EMERGENCY_STOP


def test_followers_keep_with_a_blocked_or_reversing_leader() -> None:
    fsm = behaviour_machine(S.FORMATION_TRACK)
    for ctx in (
        replace(FOLLOWER, blocked_s=1.0, leader_blocked=True),
        replace(FOLLOWER, blocked_s=1.0, leader_state=S.DEADLOCK_REVERSE),
        replace(FOLLOWER, blocked_s=1.0, reactive=False),
    ):
        assert fsm.update(ctx, 0.0) is None


def test_hysteresis_band_keeps_the_switch_from_chattering() -> None:
    fsm = behaviour_machine(S.FORMATION_TRACK)
    assert fsm.update(replace(FOLLOWER, parent_v_mps=-0.01), 0.0) is None


def test_arbitration_table_matches_the_transitions() -> None:
    used = {tr.priority for tr in behaviour_transitions()}
    assert {rule.priority for rule in ARBITRATION} <= used
    assert [r.priority for r in ARBITRATION] == sorted(
        (r.priority for r in ARBITRATION), reverse=True
    )


def test_mermaid_names_every_state_and_transition() -> None:
    machine = behaviour_machine()
    text = to_mermaid(machine, notes=STATE_NOTES)
    assert text.startswith("stateDiagram-v2\n    [*] --> HOLD\n")
    for state in State:
        assert state.value in text
    assert text.count(" --> ") >= len(machine.transitions)
    assert "STUCK --> [*]" in text


def test_an_operator_outranks_the_plan_and_the_deadlock_but_not_the_stops() -> None:
    driven = replace(LEADER, operator=True)
    for ctx, target in (
        (replace(driven, deadlock=True, retries_left=False), S.TELEOP),  # not STUCK
        (replace(driven, deadlock=True), S.TELEOP),  # not DEADLOCK_REVERSE
        (replace(driven, imminent=True), S.EMERGENCY_STOP),
        (replace(driven, estopped=True), S.ESTOPPED),
        (replace(driven, is_leader=False, parent_fresh=True), S.FORMATION_TRACK),
    ):
        event = behaviour_machine(S.NAVIGATE).update(ctx, 0.0)
        assert event is not None
        assert event.target == target, ctx
    # Stopped for an obstacle, the operator asking that way: it stays stopped, even
    # with the plan's way clear (the plan would drive it straight back to the operator).
    stopped = behaviour_machine(S.EMERGENCY_STOP)
    assert stopped.update(replace(driven, operator_clear=False), 0.0) is None
    released = stopped.update(replace(driven, operator_clear=True), 1.0)
    assert released is not None
    assert released.target == S.TELEOP
    # A slide between shapes under way finishes before an operator takes over.
    assert behaviour_machine(S.RESHAPE).update(driven, 0.0) is None


def test_the_robots_own_stop_outranks_everything_and_does_not_flap() -> None:
    fsm = behaviour_machine(S.FORMATION_TRACK)
    pressed = replace(FOLLOWER, estopped=True, bumper=True, faults=("e-stop",), stalled=True)
    event = fsm.update(pressed, 0.0)
    assert event is not None
    assert event.target == S.ESTOPPED
    for k in range(1, 5):  # a bumper and a fault while E-stopped: it stays ESTOPPED
        assert fsm.update(pressed, float(k)) is None
    released = fsm.update(replace(FOLLOWER, faults=("left drive in FAULT",)), 5.0)
    assert released is not None
    assert released.target == S.FAULT
    assert fsm.update(replace(FOLLOWER, faults=("left drive in FAULT",)), 6.0) is None
    back = fsm.update(FOLLOWER, 7.0)
    assert back is not None
    assert back.target == S.FORMATION_TRACK
