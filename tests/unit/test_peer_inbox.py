"""Who an agent takes for gone: a robot whose liveliness token went is dropped, and taken
back when it is heard again stamped well after the token went (Zenoh does not always bring
a token back with its link); what of a dead robot still waits in a ring never brings it
back."""

from __future__ import annotations

from phalanx.core.formation import resolve_formation
from phalanx.core.scenarios import formation_shape
from phalanx.runtime.peers import REVIVE_AFTER_S, PeerInbox
from phalanx.wire.messages import RobotState

FORMATION = resolve_formation(formation_shape("wedge", 3))


def _state(rid: str, stamp_s: float) -> RobotState:
    return RobotState(
        robot_id=rid, seq=1, stamp_s=stamp_s, x_m=0.0, y_m=0.0, theta_rad=0.0, v_mps=0.0,
        omega_radps=0.0, fsm_state="NAVIGATE",
    )  # fmt: skip


def _inbox() -> PeerInbox:
    return PeerInbox("r2", FORMATION, fleet="inbox", lockstep=True)


def _heard(inbox: PeerInbox, rid: str) -> list[float]:
    return [s.stamp_s for s in inbox.states.values(rid)]


def test_a_robot_heard_well_after_its_token_went_is_back() -> None:
    inbox = _inbox()
    inbox.for_step(10.0, delay_s=0.1, watched=())
    inbox.relayed([_state("r1", 9.9)])
    inbox.on_alive("r1", False)  # its link was lost (frozen past the lease)
    assert "r1" not in inbox.alive()
    inbox.relayed([_state("r1", 10.0), _state("r1", 10.0 + REVIVE_AFTER_S)])  # from before
    assert "r1" not in inbox.alive()
    assert _heard(inbox, "r1") == []
    inbox.for_step(12.0, delay_s=0.1, watched=())
    inbox.relayed([_state("r1", 11.9)])  # resumed: a new state, token or not
    assert "r1" in inbox.alive()
    assert _heard(inbox, "r1") == [11.9]


def test_a_robot_gone_before_the_first_step_comes_back_only_with_its_token() -> None:
    inbox = _inbox()
    inbox.on_alive("r3", False)
    inbox.for_step(100.0, delay_s=0.1, watched=())
    inbox.relayed([_state("r3", 99.9)])
    assert "r3" not in inbox.alive()
    inbox.on_alive("r3", True)
    inbox.relayed([_state("r3", 100.0)])
    assert "r3" in inbox.alive()
    assert _heard(inbox, "r3") == [100.0]


def test_only_another_live_robot_counts_as_heard() -> None:
    """What the agent's Relinker watches: its own state (delivered to it locally even
    when the router dropped its subscriptions) and a gone robot's old news do not count."""
    inbox = _inbox()
    inbox.for_step(10.0, delay_s=0.1, watched=())
    inbox.on_alive("r3", False)
    inbox.relayed([_state("r2", 9.9), _state("r3", 9.9)])
    assert inbox.heard_s is None
    inbox.relayed([_state("r1", 9.9)])
    assert inbox.heard_s is not None
