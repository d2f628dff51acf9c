"""The layered behaviour stack of one robot as one explicit state machine: the navigation
layer (the leader's plan, the deadlock escape, reactive avoidance and the emergency stop
on every robot) over the formation layer (a follower tracking or reversing with the robot
it follows), arbitrated by priority (the paper's figure 1, section 3).

Leadership can pass to any robot, so every robot carries both layers; its role (leader
or follower, decided by `phalanx.agents.leadership`) is an input of the guards. The
arbitration table, `ARBITRATION`, is the transition priorities in writing: a higher row
wins whenever its condition holds, whatever lower row is active.

The context is built by the agent once per step, before the update; guards only read it.
The arbitration table is generated from the transitions (`arbitration()`); docs/BEHAVIOUR.md
shows it, and a test keeps the two equal.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from phalanx.agents.behaviours.context import StackContext
from phalanx.agents.behaviours.transitions import (
    P_ARRIVE,
    P_AVOID,
    P_BEHIND,
    P_DEADLOCK,
    P_DIRECTION,
    P_ESTOP,
    P_GIVE_UP,
    P_HOLD,
    P_RESHAPE,
    P_RESUME,
    P_ROBOT,
    P_ROLE,
    P_STUCK,
    P_TELEOP,
    behaviour_transitions,
)
from phalanx.agents.fsm import StateMachine, Transition
from phalanx.core.states import State

__all__ = [
    "ARBITRATION",
    "PRIORITIES",
    "STATE_NOTES",
    "StackContext",
    "arbitration",
    "arbitration_markdown",
    "behaviour_machine",
    "behaviour_transitions",
]


@dataclass(frozen=True)
class Priority:
    """What a priority level stands for: the layer that decides, the role it applies to,
    and when its transitions fire (in words; the guards are the definition).
    """

    layer: str
    role: str
    when: str


PRIORITIES: dict[int, Priority] = {
    P_STUCK: Priority("navigation", "follower", "the formation leader is STUCK: stop for good too"),
    P_ROBOT: Priority("robot", "any",
        "the robot's driver reports an E-stop, a drive fault, a stalled wheel or a low "
        "battery: stop and stay stopped until it clears"),
    P_BEHIND: Priority("navigation", "leader",
        "the deadlock reverse meets an obstacle behind, or a robot stops for one: stop "
        "reversing and turn (a scripted leader resumes its script, as it does once backed off)"),
    P_ESTOP: Priority("navigation", "any",
        "bumper, or an obstacle within braking distance + margin in the direction of motion"),
    P_ROLE: Priority("leadership", "any",
        "leadership passed to or from this robot (handover, leader lost, newer epoch)"),
    P_HOLD: Priority("formation", "follower",
        "the formation leader or the tracked robot is gone or its state is stale"),
    P_TELEOP: Priority("operator", "leader",
        "an operator's commands keep coming (ROS 2's cmd_vel, each at most 0.5 s after the "
        "last): drive as asked, within the shape's and the robot's limits; from an emergency "
        "stop once standing with the way asked for clear"),
    P_GIVE_UP: Priority("navigation", "leader",
        "deadlock again, no retries left at this waypoint and no way to it on the map: "
        "stop for good"),
    P_DEADLOCK: Priority("navigation", "leader",
        "deadlock: every robot blocked, or the leader blocked and nobody clear to lead"),
    P_RESHAPE: Priority("navigation", "leader",
        "the shape does not fit the way ahead (or the scenario's fits again): the group "
        "drives on slowly while every slot slides to the new shape (shrunk, column, or back)"),
    P_AVOID: Priority("navigation", "follower",
        "own path blocked while the leader's is not: leave the slot, go round, come back"),
    P_DIRECTION: Priority("formation", "follower",
        "the tracked robot moves backwards / forwards (the paper's switch, figure 4a)"),
    P_ARRIVE: Priority("navigation", "leader", "the last waypoint is reached"),
    P_RESUME: Priority("navigation", "any",
        "default: go to the next waypoint (or run the script), or wander without one; "
        "a stop, a join, a detour or an operator's driving that is over returns to the plan "
        "or the slot; a new goal ends a stop at the last one"),
}  # fmt: skip


def behaviour_machine(initial: str = State.HOLD) -> StateMachine[StackContext]:
    """A fresh behaviour state machine starting in `initial`."""
    return StateMachine(
        initial=initial,
        transitions=behaviour_transitions(),
        absorbing=frozenset({State.STUCK}),
    )


@dataclass(frozen=True)
class Rule:
    """One row of the arbitration table."""

    priority: int
    behaviour: str
    layer: str
    role: str
    when: str


def arbitration(transitions: Sequence[Transition[StackContext]] | None = None) -> tuple[Rule, ...]:
    """The arbitration table, generated from the transitions: one row per priority they
    use, highest first, naming every state a transition of that priority enters.
    """
    entered: dict[int, set[str]] = {}
    for tr in behaviour_transitions() if transitions is None else transitions:
        entered.setdefault(tr.priority, set()).add(tr.target)
    order = [s.value for s in State]
    rows = []
    for priority in sorted(entered, reverse=True):
        meta = PRIORITIES[priority]
        states = sorted(entered[priority], key=order.index)
        rows.append(Rule(priority, " / ".join(states), meta.layer, meta.role, meta.when))
    return tuple(rows)


ARBITRATION = arbitration()


def arbitration_markdown(rules: Sequence[Rule] = ARBITRATION) -> str:
    """The arbitration table as markdown (highest priority first), as docs/BEHAVIOUR.md has it."""
    rows = ["| priority | behaviour | layer | role | when |", "|---:|---|---|---|---|"]
    for r in rules:
        states = " / ".join(f"`{s}`" for s in r.behaviour.split(" / "))
        rows.append(f"| {r.priority} | {states} | {r.layer} | {r.role} | {r.when} |")
    return "\n".join(rows)


STATE_NOTES: dict[str, str] = {
    State.NAVIGATE: "leader: script, or go to the next waypoint steering round obstacles",
    State.WANDER: "leader without waypoints: cruise, new heading now and then",
    State.ARRIVED: "leader at the last waypoint: stopped",
    State.DEADLOCK_REVERSE: "leader: back off in formation (followers FORMATION_REVERSE)",
    State.DEADLOCK_TURN: "leader: turn in place towards the open side",
    State.RESHAPE: "leader: the group drives on slowly while its slots slide to another shape",
    State.TELEOP: "leader: an operator drives it (ROS 2's cmd_vel), the group follows",
    State.AVOID: "follower off its slot, going round an obstacle",
    State.EMERGENCY_STOP: "brake to a standstill",
    State.STUCK: "stopped for good; the reason is in the transition log",
    State.FORMATION_TRACK: "follower tracks its slot forwards",
    State.FORMATION_REVERSE: "follower tracks its slot backwards",
    State.HOLD: "follower stopped: nobody to track",
    State.JOIN: "restarted: stopped until it hears the fleet's leader and epoch",
    State.ESTOPPED: "the robot's E-stop is engaged: stopped until it is released",
    State.FAULT: "a drive or the link to the robot reports a fault: stopped until it clears",
    State.STALLED: "a wheel is stalled: stopped until it turns freely",
    State.LOW_BATTERY: "battery below the robot's low mark: stopped until it is charged",
}
