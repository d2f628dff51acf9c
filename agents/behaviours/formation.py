"""The formation layer of a follower (figure 4a): FORMATION_TRACK while the leader moves
forwards, FORMATION_REVERSE while it backs up, HOLD while the leader's state is missing
or stale.

The switch follows the paper (section 4): it fires on the sign of the leader's
translational velocity, with a small hysteresis band so a leader crawling through zero
does not make the state chatter.
"""

from __future__ import annotations

from dataclasses import dataclass

from phalanx.agents.fsm import ANY_STATE, State, StateMachine, Transition, TransitionEvent


@dataclass
class FollowerContext:
    """What the follower's guards read, refreshed every step."""

    leader_v_mps: float = 0.0
    leader_direction: int = 1
    leader_fresh: bool = False


def _reversing(ctx: FollowerContext, threshold_mps: float) -> bool:
    return ctx.leader_fresh and ctx.leader_v_mps < -threshold_mps


def _forwards(ctx: FollowerContext, threshold_mps: float) -> bool:
    return ctx.leader_fresh and ctx.leader_v_mps > threshold_mps


def follower_transitions(threshold_mps: float) -> list[Transition[FollowerContext]]:
    """The formation layer's transitions; `threshold_mps` is the hysteresis half-band."""
    lost = "leader state missing or stale"
    return [
        Transition(ANY_STATE, State.HOLD, lambda c: not c.leader_fresh, lost, priority=100),
        Transition(
            State.FORMATION_TRACK,
            State.FORMATION_REVERSE,
            lambda c: _reversing(c, threshold_mps),
            f"leader v < -{threshold_mps:.2f} m/s",
        ),
        Transition(
            State.FORMATION_REVERSE,
            State.FORMATION_TRACK,
            lambda c: _forwards(c, threshold_mps),
            f"leader v > {threshold_mps:.2f} m/s",
        ),
        Transition(
            State.HOLD,
            State.FORMATION_REVERSE,
            lambda c: c.leader_fresh and c.leader_direction < 0,
            "leader heard again, moving backwards",
        ),
        Transition(
            State.HOLD,
            State.FORMATION_TRACK,
            lambda c: c.leader_fresh and c.leader_direction > 0,
            "leader heard again",
        ),
    ]


class FollowerBehaviour:
    """The follower's formation-layer state machine."""

    def __init__(self, threshold_mps: float) -> None:
        self.context = FollowerContext()
        self.fsm: StateMachine[FollowerContext] = StateMachine(
            initial=State.HOLD, transitions=follower_transitions(threshold_mps)
        )

    def observe(self, *, leader_v_mps: float, leader_direction: int, leader_fresh: bool) -> None:
        """Refresh the guards' context from the leader's latest state."""
        self.context.leader_v_mps = leader_v_mps
        self.context.leader_direction = leader_direction
        self.context.leader_fresh = leader_fresh

    def update(self, t_s: float) -> TransitionEvent | None:
        """Take a transition if a guard holds."""
        return self.fsm.update(self.context, t_s)

    @property
    def direction(self) -> int:
        """+1 tracking forwards, -1 reversing (what the controller and our state publish)."""
        return -1 if self.fsm.state == State.FORMATION_REVERSE else 1
