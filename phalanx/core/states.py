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


@dataclass(frozen=True, slots=True)
class TransitionEvent:
    """One logged transition: when (s), from, to, and why."""

    t_s: float
    source: str
    target: str
    reason: str
