"""Whom the world waits for at the end of a run: every robot whose report is not in and
that is alive, or went away recently enough to come back (a robot Zenoh left deaf)."""

from __future__ import annotations

import itertools
import threading
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


def test_the_end_sends_the_final_frame_again_to_the_unreported_until_they_report() -> None:
    inbox = WorldInbox(("r1", "r2", "r3"))
    inbox.alive |= {"r1", "r2", "r3"}
    sent: list[tuple[float, list[str]]] = []
    start = time.monotonic()

    def report_late() -> None:
        with inbox.cond:
            inbox.reports["r1"] = _report("r1")  # at once
            inbox.cond.notify_all()
        time.sleep(0.35)
        with inbox.cond:
            inbox.reports["r2"] = _report("r2")
            inbox.reports["r3"] = _report("r3")
            inbox.cond.notify_all()

    reporter = threading.Thread(target=report_late)
    reporter.start()
    inbox.await_reports(
        lambda robots: sent.append((time.monotonic() - start, robots)),
        timeout_s=30.0, every_s=0.1, grace_s=1.0,
    )  # fmt: skip
    took_s = time.monotonic() - start
    reporter.join(5.0)
    assert sent[0] == (sent[0][0], ["r1", "r2", "r3"])  # everyone, at once
    assert all(robots == ["r2", "r3"] for _, robots in sent[1:])  # then the missing only
    assert 2 <= len(sent) <= 6  # every 0.1 s while they were missing, not at every wake-up
    assert all(b[0] - a[0] >= 0.09 for a, b in itertools.pairwise(sent))
    assert took_s < 10.0  # the last report ended the wait, long before the timeout


def test_the_end_gives_up_at_its_timeout_when_a_report_never_comes() -> None:
    inbox = WorldInbox(("r1",))
    inbox.alive.add("r1")
    sent: list[list[str]] = []
    start = time.monotonic()
    inbox.await_reports(sent.append, timeout_s=0.3, every_s=0.1, grace_s=1.0)
    took_s = time.monotonic() - start
    assert 0.3 <= took_s < 5.0
    assert 2 <= len(sent) <= 5  # at once, then every 0.1 s (fewer if a wait overshoots)
    assert all(robots == ["r1"] for robots in sent)
