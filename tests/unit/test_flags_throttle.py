"""Which flags an agent publishes: news at once, unchanged flags only as a heartbeat."""

from __future__ import annotations

from typing import Any

from phalanx.runtime.agent import FlagsThrottle
from phalanx.wire.messages import RobotFlags


def flags(t_s: float, robot_id: str = "r2", **kw: Any) -> RobotFlags:
    base: dict[str, Any] = {
        "robot_id": robot_id,
        "seq": round(t_s * 10),
        "stamp_s": t_s,
        "fsm_state": "FORMATION_TRACK",
        "formation_leader_id": "r1",
        "profile_s": t_s,  # a follower's copy of the leader's clock: moves every step
    }
    return RobotFlags(**{**base, **kw})


def test_unchanged_flags_go_out_as_a_heartbeat_only() -> None:
    throttle = FlagsThrottle(heartbeat_s=0.2)
    sent = [t for t in (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6) if throttle.due(flags(t))]
    assert sent == [0.0, 0.2, 0.4, 0.6]
    assert throttle.skipped == 3


def test_any_decisive_change_goes_out_at_once_and_restarts_the_heartbeat() -> None:
    throttle = FlagsThrottle(heartbeat_s=0.2)
    assert throttle.due(flags(0.0))
    assert throttle.due(flags(0.1, obstacle=True, blocked_s=0.1))
    assert throttle.due(flags(0.2, obstacle=True, blocked_s=0.2))  # blocked_s grows
    assert throttle.due(flags(0.3, fsm_state="EMERGENCY_STOP"))
    assert not throttle.due(flags(0.4, fsm_state="EMERGENCY_STOP"))
    assert throttle.due(flags(0.45, fsm_state="EMERGENCY_STOP", epoch=1))


def test_the_leaders_profile_clock_is_news_every_step() -> None:
    throttle = FlagsThrottle(heartbeat_s=0.2)
    lead = [throttle.due(flags(t, "r1", fsm_state="NAVIGATE")) for t in (0.0, 0.1, 0.2)]
    assert lead == [True, True, True]
