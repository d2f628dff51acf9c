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


LEADER_STATES = frozenset(
    {
        State.NAVIGATE,
        State.WANDER,
        State.ARRIVED,
        State.DEADLOCK_REVERSE,
        State.DEADLOCK_TURN,
        State.RESHAPE,
    }
)
FOLLOWER_STATES = frozenset(
    {State.FORMATION_TRACK, State.FORMATION_REVERSE, State.AVOID, State.HOLD}
)
# The robot's own conditions, from its driver's status: E-stop, drive fault, stall, battery.
ROBOT_STATES = frozenset({State.ESTOPPED, State.FAULT, State.STALLED, State.LOW_BATTERY})
# A robot in one of these has left its slot: nobody may track it (leadership's rule 5).
OUT_OF_FORMATION = (
    frozenset({State.AVOID, State.EMERGENCY_STOP, State.JOIN, State.STUCK}) | ROBOT_STATES
)
DEADLOCK_STATES = frozenset({State.DEADLOCK_REVERSE, State.DEADLOCK_TURN})
