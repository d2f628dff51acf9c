"""The behaviour states of a robot, and the record of a transition between two of them.

The names are shared vocabulary: the behaviour stack (`phalanx.agents`) moves between
them, the wire carries them as text, and the analysis and figures read them back.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum


class State(StrEnum):
    """Behaviour states of the navigation and formation layers (one machine per robot:
    the leader runs navigation states, followers formation states, and leadership can
    move a robot from one set to the other).
    """

    # navigation layer, the formation leader: its plan and the deadlock escape
    NAVIGATE = "NAVIGATE"
    WANDER = "WANDER"
    ARRIVED = "ARRIVED"
    DEADLOCK_REVERSE = "DEADLOCK_REVERSE"
    DEADLOCK_TURN = "DEADLOCK_TURN"
    RESHAPE = "RESHAPE"  # the group drives on slowly while its slots slide to another shape
    TELEOP = "TELEOP"  # an operator drives the leader (ROS 2's cmd_vel), the group follows
    # navigation layer, every robot: reactive avoidance and safety
    AVOID = "AVOID"
    EMERGENCY_STOP = "EMERGENCY_STOP"
    STUCK = "STUCK"
    # formation layer, followers (figure 4a)
    FORMATION_TRACK = "FORMATION_TRACK"
    FORMATION_REVERSE = "FORMATION_REVERSE"
    # shared
    HOLD = "HOLD"
    JOIN = "JOIN"
    # the robot itself, any role: what its driver reports stops it
    ESTOPPED = "ESTOPPED"
    FAULT = "FAULT"
    STALLED = "STALLED"
    LOW_BATTERY = "LOW_BATTERY"


@dataclass(frozen=True, slots=True)
class TransitionEvent:
    """One logged transition: when (s), from, to, and why."""

    t_s: float
    source: str
    target: str
    reason: str


class StateGroup(StrEnum):
    """The superstates the behaviour states are grouped in, as a Stateflow chart nests
    them (`phalanx fsm` draws one box per group).
    """

    DRIVING = "driving"  # the leader drives the group: plan, operator, reshaping, deadlock escape
    FORMATION = "formation"  # a follower in (or making for) its slot, or waiting for one
    SAFETY = "safety"  # stopped by what is around it, until the fleet is heard, or for good
    ROBOT = "robot faults"  # stopped by what the robot's own driver reports


# Every state in exactly one group (a test checks it): the one definition of the grouping.
STATE_GROUPS: dict[State, StateGroup] = {
    State.NAVIGATE: StateGroup.DRIVING,
    State.WANDER: StateGroup.DRIVING,
    State.ARRIVED: StateGroup.DRIVING,
    State.RESHAPE: StateGroup.DRIVING,
    State.DEADLOCK_REVERSE: StateGroup.DRIVING,
    State.DEADLOCK_TURN: StateGroup.DRIVING,
    State.TELEOP: StateGroup.DRIVING,
    State.FORMATION_TRACK: StateGroup.FORMATION,
    State.FORMATION_REVERSE: StateGroup.FORMATION,
    State.AVOID: StateGroup.FORMATION,
    State.HOLD: StateGroup.FORMATION,
    State.EMERGENCY_STOP: StateGroup.SAFETY,
    State.JOIN: StateGroup.SAFETY,
    State.STUCK: StateGroup.SAFETY,
    State.ESTOPPED: StateGroup.ROBOT,
    State.FAULT: StateGroup.ROBOT,
    State.STALLED: StateGroup.ROBOT,
    State.LOW_BATTERY: StateGroup.ROBOT,
}


def states_of(group: StateGroup) -> frozenset[State]:
    """The states of `group`."""
    return frozenset(s for s, g in STATE_GROUPS.items() if g == group)


# The states a leader drives in, and a follower's: leadership moves a robot between them.
LEADER_STATES = states_of(StateGroup.DRIVING)
FOLLOWER_STATES = states_of(StateGroup.FORMATION)
# The robot's own conditions, from its driver's status: E-stop, drive fault, stall, battery.
ROBOT_STATES = states_of(StateGroup.ROBOT)
# The states the paper has: the formation layer of its Stateflow chart (figure 4a: the
# tracking controller, and the geometric controller that drives backwards) and the
# behaviours of its layered architecture (figure 1, section 3: navigation, obstacle
# avoidance, and the backward motion out of a deadlock). The rest is ours.
PAPER_STATES = frozenset(
    {
        State.FORMATION_TRACK,
        State.FORMATION_REVERSE,
        State.NAVIGATE,
        State.AVOID,
        State.DEADLOCK_REVERSE,
    }
)
# A robot in one of these has left its slot: nobody may track it (leadership's rule 5).
OUT_OF_FORMATION = (
    frozenset({State.AVOID, State.EMERGENCY_STOP, State.JOIN, State.STUCK}) | ROBOT_STATES
)
DEADLOCK_STATES = frozenset({State.DEADLOCK_REVERSE, State.DEADLOCK_TURN})
