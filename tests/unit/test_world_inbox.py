"""Whom the world waits for at the end of a run: every robot whose report is not in and
that is alive, or went away recently enough to come back (a robot Zenoh left deaf)."""

from __future__ import annotations

import time

from phalanx.core.geometry import Twist2D
from phalanx.runtime.world_inbox import WorldInbox
from phalanx.wire.messages import AgentReport


def _report(robot_id: str) -> AgentReport:
    return AgentReport(
        robot_id=robot_id,
        steps=10,
        saturations=0,
        accel_limited=0,
        dropped_messages=0,
        late_peer_steps=0,
    )


def test_the_end_waits_for_live_robots_and_the_recently_gone_not_for_the_long_gone() -> None:
    inbox = WorldInbox(("r1", "r2", "r3", "r4"))
    inbox.alive |= {"r1", "r2"}
    inbox.gone("r3", tick=140)  # its token went a moment ago: it may be back
    inbox.gone("r4", tick=3)
    inbox.lost_s["r4"] -= 60.0  # ... and this one a minute ago
    assert inbox.unreported(10.0) == {"r1", "r2", "r3"}
    inbox.reports["r1"] = _report("r1")
    inbox.reports["r3"] = _report("r3")
    assert inbox.unreported(10.0) == {"r2"}
    assert inbox.lost == [("r3", 140), ("r4", 3)]


def test_a_robot_gone_before_the_start_is_not_lost_to_the_run_but_still_waited_for() -> None:
    inbox = WorldInbox(("r1",))
    inbox.latest["r1"] = Twist2D(0.3, 0.0)
    inbox.gone("r1", tick=None)
    assert inbox.lost == []
    assert "r1" not in inbox.latest  # a process restarted in its place starts from nothing
    assert inbox.unreported(10.0) == {"r1"}
    time.sleep(0.02)
    assert inbox.unreported(0.01) == set()
