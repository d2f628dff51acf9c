"""A session that a router stopped serving gets back by re-opening: `FleetSession.relink`
declares everything again on a new Zenoh session, and `Relinker` decides when, from
what its owner stopped hearing.

The deafness Zenoh sometimes leaves after a router froze past the lease (the client is
attached, the router dropped its declarations) is made here on purpose: the robot's
declarations are undeclared behind its session's back, which is what the router did.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from agentlab import framed_agent

from phalanx.core.errors import TransportError
from phalanx.wire.messages import AgentEvent
from phalanx.wire.relink import Relinker
from phalanx.wire.transport import (
    FleetSession,
    TransportConfig,
    free_tcp_port,
    loopback_endpoint,
    open_session,
)

pytestmark = pytest.mark.integration
EVENT = "phalanx/t/robots/r1/event"
TO_ROBOT = "phalanx/t/robots/r2/event"
ALIVE = "phalanx/t/alive/r1"
WAIT_S = 5.0


def _event(reason: str, robot: str = "r1") -> AgentEvent:
    return AgentEvent(robot_id=robot, t_s=1.0, source="HOLD", target="NAVIGATE", reason=reason)


class Heard:
    """The reasons of the events a session heard, and a wake-up on each."""

    def __init__(self) -> None:
        self.reasons: list[str] = []
        self.arrived = threading.Event()

    def __call__(self, _key: str, event: AgentEvent) -> None:
        self.reasons.append(event.reason)
        self.arrived.set()

    def delivered(self, send: FleetSession, key: str, reason: str, robot: str) -> bool:
        """Whether `reason` sent on `key` arrives (resent until the route is there)."""
        for _ in range(round(WAIT_S / 0.1)):
            self.arrived.clear()
            send.publish(key, _event(reason, robot), reliable_block=True)
            if self.arrived.wait(0.1) and reason in self.reasons:
                return True
        return False


@contextmanager
def _fabric() -> Iterator[tuple[FleetSession, FleetSession, TransportConfig]]:
    """A router, and a watcher session connected to it; the robot's configuration."""
    endpoint = loopback_endpoint(free_tcp_port())
    router = TransportConfig(mode="router", listen=(endpoint,), lowlatency=True)
    client = TransportConfig(mode="client", connect=(endpoint,), lowlatency=True)
    with open_session(router) as world, open_session(client) as watcher:
        yield world, watcher, client


def _alive(watcher: FleetSession) -> bool:
    replies = watcher.zenoh.liveliness().get(ALIVE, timeout=1.0)
    return any(reply.ok is not None for reply in replies)


def _deafen(robot: FleetSession) -> None:
    """What the router did: forget every declaration of the robot's session."""
    for _declare, entity in robot._keep:
        entity.undeclare()


def test_a_deaf_session_hears_speaks_and_is_seen_again_once_relinked() -> None:
    with _fabric() as (_world, watcher, client), open_session(client) as robot:
        at_watcher, at_robot = Heard(), Heard()
        watcher.subscribe(EVENT, AgentEvent, at_watcher)
        robot.subscribe(TO_ROBOT, AgentEvent, at_robot)
        robot.declare_alive(ALIVE)
        robot.serve_status("phalanx/t/status/r1", lambda: {"robot": "r1"})
        assert at_robot.delivered(watcher, TO_ROBOT, "before", "r2")
        zid = str(robot.zenoh.info.zid())

        _deafen(robot)
        assert not at_robot.delivered(watcher, TO_ROBOT, "deaf", "r2")
        assert not _alive(watcher)

        assert robot.relink()
        assert robot.relinks == 1
        assert str(robot.zenoh.info.zid()) != zid  # a new session, not the old one patched
        assert at_robot.delivered(watcher, TO_ROBOT, "after", "r2")  # its subscription
        assert at_watcher.delivered(robot, EVENT, "spoken", "r1")  # its publishers
        assert _alive(watcher)  # its liveliness token
        assert watcher.query_status("phalanx/t/status/r1") == [{"robot": "r1"}]


def test_a_relink_with_no_router_to_reach_keeps_the_session() -> None:
    endpoint = loopback_endpoint(free_tcp_port())
    router = open_session(TransportConfig(mode="router", listen=(endpoint,)))
    try:
        robot = open_session(TransportConfig(mode="client", connect=(endpoint,)))
    finally:
        router.close()
    with robot:
        zid = str(robot.zenoh.info.zid())
        assert not robot.relink(open_timeout_s=0.5)  # nobody listens: the open fails
        assert robot.relinks == 0
        assert str(robot.zenoh.info.zid()) == zid
        robot.publish(EVENT, _event("still usable"))


def test_a_session_that_could_not_declare_everything_again_refuses_to_relink() -> None:
    endpoint = loopback_endpoint(free_tcp_port())
    router = TransportConfig(mode="router", listen=(endpoint,))
    with open_session(router) as listening, pytest.raises(TransportError, match="listening"):
        listening.relink()
    with _fabric() as (_world, watcher, _client):
        watcher.hold(watcher.zenoh.declare_subscriber(EVENT, lambda _s: None))
        assert not watcher.can_relink
        with pytest.raises(TransportError, match="raw Zenoh entities"):
            watcher.relink()


class Clock:
    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s


def test_the_relinker_waits_for_silence_then_thins_its_attempts_out() -> None:
    with _fabric() as (_world, _watcher, client), open_session(client) as robot:
        clock = Clock()
        heard: list[float | None] = [None]
        relinker = Relinker(robot, lambda: heard[0], after_s=5.0, max_after_s=12.0, clock=clock)
        clock.now_s += 60.0
        assert not relinker.check()  # nothing expected yet: no silence is suspect
        heard[0] = clock.now_s
        clock.now_s += 4.9
        assert not relinker.check()
        clock.now_s += 0.2
        assert relinker.check()  # 5.1 s of silence
        assert robot.relinks == 1
        clock.now_s += 5.1
        assert not relinker.check()  # still silent: the next attempt waits twice as long
        clock.now_s += 5.0
        assert relinker.check()
        clock.now_s += 12.1
        assert relinker.check()  # at most max_after_s apart
        clock.now_s += 1.0
        heard[0] = clock.now_s  # heard again: the wait is back to after_s
        clock.now_s += 4.9
        assert not relinker.check()
        clock.now_s += 0.2
        assert relinker.check()
        assert robot.relinks == 4


def test_the_relinker_thread_ends_with_it() -> None:
    with _fabric() as (_world, _watcher, client), open_session(client) as robot:
        with Relinker(robot, lambda: None) as relinker:
            relinker.start()
            thread = relinker._thread
            assert thread is not None
            assert thread.is_alive()
        assert not thread.is_alive()


class Stepping:
    """A clock that moves `step_s` at every reading."""

    def __init__(self, step_s: float) -> None:
        self.now_s, self.step_s = 100.0, step_s

    def __call__(self) -> float:
        self.now_s += self.step_s
        return self.now_s


@pytest.mark.parametrize(("step_s", "relinked"), [(0.2, True), (2.0, False)])
def test_a_watch_that_wakes_late_waits_for_what_arrived_meanwhile(
    step_s: float, relinked: bool
) -> None:
    """Woken late (this process was frozen: frames may be on their way in), the watch
    decides on its next wake-up, not on the silence the freeze made."""
    with _fabric() as (_world, _watcher, client), open_session(client) as robot:
        clock = Stepping(step_s)
        with Relinker(robot, lambda: 0.0, after_s=1.0, clock=clock) as relinker:
            relinker.start()
            deadline = time.monotonic() + 1.5
            while time.monotonic() < deadline and robot.relinks == 0:
                time.sleep(0.05)
        assert (robot.relinks > 0) == relinked


def test_an_agent_left_deaf_re_opens_its_session_and_steps_on_the_worlds_frames() -> None:
    """The whole way back in one agent: the router forgets it (made as above), the world's
    frames stop reaching it, 5 s later it re-opens its session and steps on them again."""
    with framed_agent("deaf", "realtime", lowlatency=True) as it:
        runtime = it.runtime
        assert it.frames_until(lambda: runtime.steps >= 5, 20.0)
        session = runtime._session
        assert session is not None
        _deafen(session)
        deaf_at = runtime.steps
        assert it.frames_until(lambda: session.relinks == 1, 10.0)
        assert runtime.steps <= deaf_at + 2  # nothing heard meanwhile (a step, a frame in)
        assert it.frames_until(lambda: runtime.steps >= deaf_at + 5, 10.0)
