"""What agents send the world process, as its Zenoh callbacks file it, and the lockstep
tick's bookkeeping on it: each robot's answer for a tick (the command it executes from
the tick on), the wait for a tick's answers, and the states the next frames carry to the
other robots; and the run's record of leadership handovers (`LeaderLog`).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import defaultdict, deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from phalanx.core.geometry import Twist2D
from phalanx.wire.messages import AgentEvent, AgentReport, LeaderAnnouncement, RobotState

log = logging.getLogger("phalanx.world")

# Transitions and leadership handovers kept for the run's log; more (a flood) are
# dropped and counted.
MAX_LOG_ENTRIES = 100_000
# Leadership announcements taken per announced leader in any second; more are refused and
# counted (a leader announces once a change, and changes come seconds apart).
ANNOUNCEMENTS_PER_S = 2
# A robot counts towards the fleet's agreement at a tick with its newest state of up to this
# many ticks before (one not heard that long is gone; one a tick behind still votes).
VOTE_TICKS = 10


def _newest_at(states: Mapping[int, RobotState], tick: int) -> RobotState | None:
    """A robot's newest state at `tick` or up to VOTE_TICKS before (None: not there)."""
    for k in range(tick, tick - VOTE_TICKS - 1, -1):
        state = states.get(k)
        if state is not None:
            return state
    return None


@dataclass
class LeaderLog:
    """The fleet's leadership handovers as the run records them (metrics.json's
    `runtime.leadership`).

    The leader key does not say who sent an announcement, so an announcement only
    proposes: `(epoch, leader)` is recorded once the fleet stands behind it, as every
    robot's own rule does: a later epoch than the last recorded, held at some tick by
    the named leader's own state and by more than half the robots heard around then
    (each by its newest state of up to VOTE_TICKS before). Per announced leader at most
    ANNOUNCEMENTS_PER_S a second are looked at and one proposal waits (the earliest
    epoch, then the first heard); every refused one is counted in `refused`. Only
    `states` (by robot, by tick) is read, never changed.
    """

    ids: tuple[str, ...]
    states: Mapping[str, Mapping[int, RobotState]]
    entries: list[LeaderAnnouncement] = field(default_factory=list)
    epoch: int = 0
    leader_id: str = ""  # the leader last recorded ("": the formation's root, not recorded)
    refused: int = 0
    _pending: dict[str, tuple[LeaderAnnouncement, int]] = field(default_factory=dict)
    _heard_s: dict[str, deque[float]] = field(default_factory=dict)

    def propose(self, announcement: LeaderAnnouncement, now_s: float) -> str:
        """Take `announcement` (at monotonic time `now_s`) as a proposal; why it is
        refused ("" if it waits for, or got, the fleet's agreement).
        """
        why = self._refusal(announcement, now_s)
        if why:
            self.refused += 1
            return why
        waiting = self._pending.get(announcement.leader_id)
        if waiting is None or announcement.epoch < waiting[0].epoch:
            self._pending[announcement.leader_id] = (announcement, -1)
        self.settle()
        return ""

    def _refusal(self, announcement: LeaderAnnouncement, now_s: float) -> str:
        leader = announcement.leader_id
        if leader not in self.ids:
            return f"announced leader {leader!r} is no robot of this fleet"
        if announcement.epoch <= self.epoch:
            return f"epoch {announcement.epoch} is not after {self.epoch}"
        heard = self._heard_s.setdefault(leader, deque(maxlen=ANNOUNCEMENTS_PER_S))
        if len(heard) == heard.maxlen and now_s - heard[0] < 1.0:
            return f"over {ANNOUNCEMENTS_PER_S} announcements of {leader} a second"
        heard.append(now_s)
        return ""

    def settle(self) -> list[LeaderAnnouncement]:
        """Record the waiting proposals the fleet now stands behind, lowest epoch first
        (each looks only at the ticks it has not settled); the log.
        """
        for leader in sorted(self._pending, key=lambda r: self._pending[r][0].epoch):
            announcement, seen = self._pending[leader]
            if announcement.epoch <= self.epoch:
                continue
            agreed, seen = self._agreed(announcement, seen)
            self._pending[leader] = (announcement, seen)
            if agreed:
                self._record(announcement)
        self._pending = {r: p for r, p in self._pending.items() if p[0].epoch > self.epoch}
        return self.entries

    def _agreed(self, announcement: LeaderAnnouncement, seen: int) -> tuple[bool, int]:
        """Whether a tick after `seen` has the leader's own state and most robots' name
        `announcement`'s pair; where to look from next time.
        """
        claim = (announcement.epoch, announcement.leader_id)
        own = self.states.get(announcement.leader_id, {})
        robots = list(self.states.values())  # (copies: safe while a Zenoh thread files)
        newest = -1
        for tick in reversed(list(own)):  # (filed in tick order: stop at what was seen)
            if tick <= seen:
                break
            newest = max(newest, tick)
            state = own.get(tick)
            if state is None or (state.epoch, state.formation_leader_id) != claim:
                continue
            votes = [v for v in (_newest_at(r, tick) for r in robots) if v is not None]
            held = sum((s.epoch, s.formation_leader_id) == claim for s in votes)
            if 2 * held > len(votes):
                return True, newest
        return False, max(seen, newest - VOTE_TICKS)  # (others' states of those may come)

    def _record(self, announcement: LeaderAnnouncement) -> None:
        previous = self.leader_id or announcement.previous_id
        entry = announcement.model_copy(update={"previous_id": previous})
        if len(self.entries) < MAX_LOG_ENTRIES:
            self.entries.append(entry)
        self.epoch, self.leader_id = announcement.epoch, announcement.leader_id


@dataclass
class WorldInbox:
    """What the fleet's robots `ids` sent (thread-safe: hold `cond`, unless a method
    says it takes it).
    """

    ids: tuple[str, ...]
    cond: threading.Condition = field(default_factory=threading.Condition)
    commands: dict[int, dict[str, Twist2D]] = field(default_factory=lambda: defaultdict(dict))
    latest: dict[str, Twist2D] = field(default_factory=dict)
    states: dict[str, dict[int, RobotState]] = field(default_factory=lambda: defaultdict(dict))
    events: list[AgentEvent] = field(default_factory=list)
    reports: dict[str, AgentReport] = field(default_factory=dict)
    alive: set[str] = field(default_factory=set)
    leaders: LeaderLog = field(init=False)  # the handovers the fleet stood behind
    overflow: int = 0  # events beyond MAX_LOG_ENTRIES
    lost: list[tuple[str, int]] = field(default_factory=list)  # (robot, tick) it went away
    lost_s: dict[str, float] = field(default_factory=dict)  # when it last went (monotonic)
    sent_at: dict[int, float] = field(default_factory=dict)  # when a tick's frames went out
    response_s: list[float] = field(default_factory=list)  # frames out -> each answer in
    relayed: dict[str, int] = field(default_factory=dict)  # newest tick passed on, by robot
    heard_s: float | None = None  # when a robot's message was last taken (monotonic)

    def __post_init__(self) -> None:
        self.leaders = LeaderLog(self.ids, self.states)

    def keep(self, entries: list[Any], value: object) -> None:
        """Append to the run's log, up to MAX_LOG_ENTRIES."""
        if len(entries) < MAX_LOG_ENTRIES:
            entries.append(value)
        else:
            self.overflow += 1

    def heard(self, robot_id: str, tick: int, now: int) -> None:
        """A message of `robot_id`'s for `tick`, the world being at tick `now`: one for
        the tick before or later proves the robot is there, whatever its liveliness
        token says.

        Zenoh does not always bring a token back when a lost link comes back: a world
        frozen past the lease then waited for no answer and no report of that robot's. A
        robot that died sends nothing after its token's loss.
        """
        self.heard_s = time.monotonic()
        if tick >= now - 1 and robot_id not in self.alive:
            self.alive.add(robot_id)
            log.warning(
                "robot %s is heard again at tick %d (its liveliness token is not)", robot_id, now
            )

    def gone(self, robot_id: str, tick: int | None) -> None:
        """`robot_id`'s liveliness went (at `tick` of the run; None: before it started).
        A process restarted in its place must not inherit its predecessor's command.
        """
        self.latest.pop(robot_id, None)
        self.lost_s[robot_id] = time.monotonic()
        if tick is not None:
            self.lost.append((robot_id, tick))

    def unreported(self, grace_s: float) -> set[str]:
        """The robots whose report is not in (takes `cond`): the live ones, and those
        whose liveliness went within the last `grace_s`. A robot Zenoh left deaf loses
        its token and re-opens its session a few seconds later (`phalanx.wire.relink`):
        it may still hear the final frame, sent again, and report.
        """
        now = time.monotonic()
        with self.cond:
            return {
                r
                for r in self.ids
                if r not in self.reports
                and (r in self.alive or now - self.lost_s.get(r, -math.inf) <= grace_s)
            }

    def await_reports(
        self,
        send: Callable[[list[str]], None],
        *,
        timeout_s: float,
        every_s: float,
        grace_s: float,
    ) -> None:
        """The run's end (takes `cond` to wait): `send` the final frame to every robot,
        then again every `every_s` to those `unreported(grace_s)`, until none is or
        `timeout_s` has passed. A report wakes the wait at once (`cond` is re-entrant:
        `unreported` takes it again inside the wait).
        """
        now = time.monotonic()
        deadline, waiting, sent_s = now + timeout_s, sorted(self.ids), -math.inf
        while waiting:
            if now - sent_s >= every_s:
                send(waiting)
                sent_s = now
            if now >= deadline:
                return
            with self.cond:  # (a report that came since `waiting` was taken: no wait)
                missing = set(waiting)
                self.cond.wait_for(
                    lambda: self.unreported(grace_s) != missing,  # noqa: B023 (used at once)
                    min(sent_s + every_s, deadline) - now,
                )
            waiting, now = sorted(self.unreported(grace_s)), time.monotonic()

    def answer(self, robot_id: str, tick: int, command: Twist2D) -> None:
        """Robot `robot_id`'s command for `tick`; the tick's waiter is woken once, when
        every live robot has answered (not once a robot).
        """
        answers = self.commands[tick]
        sent = self.sent_at.get(tick)
        if sent is not None and robot_id not in answers:
            self.response_s.append(time.monotonic() - sent)
        answers[robot_id] = command
        self.latest[robot_id] = command
        if len(answers) >= len(self.alive):
            self.cond.notify_all()

    def await_states(self, k: int, timeout_s: float) -> set[str]:
        """Wait (takes `cond`) until every live robot's state of tick `k` is in, or
        `timeout_s`; the live robots whose state is not.
        """
        deadline = time.monotonic() + timeout_s
        with self.cond:
            while True:
                missing = {r for r in self.ids if r in self.alive and k not in self.states[r]}
                remaining = deadline - time.monotonic()
                if not missing or remaining <= 0.0:
                    return missing
                self.cond.wait(remaining)

    def relay(self, k: int, back: int) -> tuple[RobotState, ...]:
        """Each robot's newest state stamped before tick `k` not yet passed on, looked
        for `back` ticks back at most (takes `cond`).
        """
        out = []
        with self.cond:
            for rid in self.ids:
                states, last = self.states[rid], self.relayed.get(rid, -1)
                for tick in range(k - 1, max(last, k - 1 - back), -1):
                    state = states.get(tick)
                    if state is not None:
                        out.append(state)
                        self.relayed[rid] = tick
                        break
        return tuple(out)
