"""What an agent process hears of its fleet, and what of its own it sends.

Every robot's small flags are heard by every robot (leadership and deadlock are decided
from them on every robot); a robot's full state only by the robots that may track it,
those on its follow-tree path to the current leader. In lockstep (one machine,
deterministic runs) every state is taken instead, so the robot tracked after a
leadership change has a state from the very same tick, and a step first waits (bounded)
for the states the batch runner would hand it (published `comm_delay_s` earlier).

A navigating robot's sonar scans go to every robot too (`ScanInbox`): each adds the
fleet's scans to its copy of the shared map (`phalanx.agents.navigation.fleet_map`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Iterable
from typing import TypeVar

from phalanx.core.formation import Formation
from phalanx.core.peers import PeerFlags, PeerState, Scan
from phalanx.wire.bounds import FleetBounds
from phalanx.wire.delivery import History, Polled
from phalanx.wire.keys import robot_key, robots_key
from phalanx.wire.messages import RobotFlags, RobotState, ScanMessage
from phalanx.wire.transport import FleetSession

log = logging.getLogger("phalanx.agent")

EPS_S = 1e-6
# A robot whose liveliness token went is taken back when a message of its arrives stamped
# this much later than the step at which the token went (s, on the fleet clock): Zenoh
# does not always bring a token back when a lost link comes back. A robot that died sends
# nothing newer (what of it still waits in a ring is older; the margin covers the clocks'
# offsets in real time).
REVIVE_AFTER_S = 1.0
# An epoch grows by one per leadership change: a claim this far above the highest heard
# is no peer's (a fleet would need years of handovers), and its message is refused and
# counted (the top of the range would otherwise stick as the highest heard). A claim
# within it is the leadership rule's to adopt or refuse (`phalanx.agents.leadership`:
# only the next epoch, to the rule's pick, or what most live robots hold).
EPOCH_WINDOW = 2**16
# Flags (or states) held per robot between two steps before the oldest are dropped (one
# arrives per robot and control period; the ring absorbs a late step).
RING_PER_ROBOT = 8
S = TypeVar("S", PeerState, PeerFlags)


def pick_state(states: Iterable[S], not_after_s: float) -> S | None:
    """The newest state stamped no later than `not_after_s`."""
    chosen = None
    for state in states:
        if state.stamp_s <= not_after_s + EPS_S and (
            chosen is None or state.stamp_s > chosen.stamp_s
        ):
            chosen = state
    return chosen


def _has_state(states: Iterable[PeerState], not_after_s: float) -> bool:
    return any(abs(s.stamp_s - not_after_s) <= EPS_S or s.stamp_s > not_after_s for s in states)


# What flags say, as far as other robots decide on it: not who sent them, their sequence
# number or stamp, nor a follower's copy of the leader's profile clock (only the leader's
# is read).
_FLAGS_VOLATILE = frozenset({"robot_id", "seq", "stamp_s", "profile_s"})
_FLAGS_DECISIVE = tuple(
    f.name for f in dataclasses.fields(PeerFlags) if f.name not in _FLAGS_VOLATILE
)


class FlagsThrottle:
    """Decides which flags go out: those that say something new, and unchanged ones as a
    heartbeat every `heartbeat_s` (every robot hears every robot: unchanged flags at
    every step would cost the fleet n^2 messages a period for nothing).
    """

    def __init__(self, heartbeat_s: float) -> None:
        self.heartbeat_s = heartbeat_s
        self.skipped = 0
        self._sent: tuple[float, tuple[object, ...]] | None = None  # when, what

    def due(self, flags: PeerFlags) -> bool:
        """Whether to publish `flags` (if so, they count as sent)."""
        content = tuple(getattr(flags, f) for f in _FLAGS_DECISIVE)
        if flags.formation_leader_id == flags.robot_id:
            content += (flags.profile_s,)
        sent = self._sent
        if (
            sent is None
            or content != sent[1]
            or flags.stamp_s - sent[0] >= self.heartbeat_s - EPS_S
        ):
            self._sent = (flags.stamp_s, content)
            return True
        self.skipped += 1
        return False


class PeerInbox:
    """The states and flags an agent process has heard, by robot, and who is gone."""

    def __init__(
        self,
        robot_id: str,
        formation: Formation,
        *,
        fleet: str,
        lockstep: bool,
        bounds: FleetBounds | None = None,
    ) -> None:
        self.robot_id = robot_id
        self.formation = formation
        self.fleet = fleet
        self.lockstep = lockstep
        self.bounds = bounds  # what every state and flags are held against
        self.states = History(depth=16)
        self.flags = History(depth=4)  # one a period per robot; real time needs the newest
        self.dead: dict[str, float] = {}  # robot -> the step's time when its token went
        self._step_s = math.inf  # the latest step's time (none yet: nobody comes back)
        self.late_steps = 0
        self.max_epoch = 0  # the highest epoch heard (or held) so far
        self.heard_s: float | None = None  # when another robot's message was last taken
        self._session: FleetSession | None = None
        self._flag_ring: Polled[RobotFlags] | None = None
        self._state_rings: list[Polled[RobotState]] = []
        self._subscribed: set[str] = set()

    def attach(self, session: FleetSession, watched: tuple[str, ...]) -> None:
        """Subscribe to every robot's flags (drained from a ring once per step, no wake-up
        per message) and the states of `watched`; in lockstep to nothing: the world's
        frames carry every state (`relayed`).
        """
        self._session = session
        if self.lockstep:
            return
        capacity = RING_PER_ROBOT * len(self.formation.robot_ids)
        self._flag_ring = session.subscribe_polled(
            robots_key(self.fleet, "flags"), RobotFlags, capacity, context=self.bounds,
            rate_hz=self._rate_hz,
        )  # fmt: skip
        self.follow(watched)

    @property
    def _rate_hz(self) -> float | None:
        """How often one robot publishes on one key (real time only: the rings are for
        agents on their own clock): a flood beyond a few times that is dropped and counted.
        """
        return None if self.bounds is None else 1.0 / self.bounds.dt_s

    def follow(self, watched: tuple[str, ...]) -> None:
        """Subscribe to the states of the robots in `watched` not yet heard."""
        if self._session is None:
            return
        for peer in watched:
            if peer not in self._subscribed:
                self._subscribed.add(peer)
                key = robot_key(self.fleet, peer, "state")
                ring = self._session.subscribe_polled(
                    key, RobotState, RING_PER_ROBOT, context=self.bounds, rate_hz=self._rate_hz
                )
                self._state_rings.append(ring)

    def drain(self) -> None:
        """Take what waits in the rings."""
        if self._flag_ring is not None:
            self._flag_ring.drain(self._on_flags)
        for ring in self._state_rings:
            ring.drain(self._on_state)

    def relayed(self, states: Iterable[RobotState]) -> None:
        """The other robots' states a lockstep frame carried (checked with the frame)."""
        for state in states:
            self._on_state("", state)

    # (A message on another robot's key never gets here: the session rejects it.)
    def _on_state(self, _key: str, state: RobotState) -> None:
        if self._heard(state):
            self.states.push(state.robot_id, state.peer())

    def _on_flags(self, _key: str, flags: RobotFlags) -> None:
        if self._heard(flags):
            self.flags.push(flags.robot_id, flags.peer())

    def _heard(self, message: RobotState | RobotFlags) -> bool:
        """Whether to take a peer's message: not our own, not a robot known gone, and an
        epoch within EPOCH_WINDOW of the highest heard (else refused and counted).
        """
        if message.robot_id == self.robot_id or not self._back(message):
            return False
        if message.epoch > self.max_epoch + EPOCH_WINDOW:
            if self._session is not None:
                name = type(message).__name__
                why = f"epoch {message.epoch} jumps from {self.max_epoch}"
                self._session.stats.count("rejected", name, f"{name} of {message.robot_id}: {why}")
            return False
        self.max_epoch = max(self.max_epoch, message.epoch)
        self.heard_s = time.monotonic()
        return True

    def keep_own(self, state: PeerState, flags: PeerFlags) -> None:
        """The robot's own state and flags, as published: part of what the next step
        decides on.
        """
        self.flags.push(self.robot_id, flags)
        self.states.push(self.robot_id, state)
        self.max_epoch = max(self.max_epoch, state.epoch)

    def _back(self, message: RobotState | RobotFlags) -> bool:
        """Whether `message`'s robot is not known gone, or is back (REVIVE_AFTER_S)."""
        gone = self.dead.get(message.robot_id)
        if gone is None:
            return True
        if message.stamp_s <= gone + REVIVE_AFTER_S:
            return False
        self.dead.pop(message.robot_id, None)
        log.warning("robot %s is heard again (its liveliness token is not)", message.robot_id)
        return True

    def on_alive(self, robot: str, alive: bool) -> None:
        """A robot's process appeared or went (its liveliness token)."""
        if robot == self.robot_id or robot not in self.formation.positions:
            return
        if alive:
            self.dead.pop(robot, None)
        else:
            self.dead[robot] = self._step_s
            self.states.forget(robot)
            self.flags.forget(robot)

    def alive(self) -> list[str]:
        """The fleet's robots not known to be gone."""
        return [r for r in self.formation.robot_ids if r not in self.dead]

    def for_step(
        self, t_s: float, *, delay_s: float, watched: tuple[str, ...]
    ) -> tuple[dict[str, PeerState], dict[str, PeerFlags]]:
        """The states (and, in real time, flags) the agent gets for the step at `t_s`.
        In lockstep every live robot's state `delay_s` old is due with the step's frame
        (the world waited for them); a step without one is counted late.
        """
        self._step_s = t_s
        if not self.lockstep:
            states = {p: pick_state(self.states.values(p), t_s) for p in watched}
            flags = {p: pick_state(self.flags.values(p), t_s) for p in self.alive()}
            return (
                {p: s for p, s in states.items() if s is not None},
                {p: f for p, f in flags.items() if f is not None},
            )
        not_after = t_s - delay_s
        needed = [p for p in self.alive() if p != self.robot_id]
        if not_after >= -EPS_S and not all(
            _has_state(self.states.values(p), not_after) for p in needed
        ):
            self.late_steps += 1
        chosen = {p: pick_state(self.states.values(p), not_after) for p in self.alive()}
        return {p: s for p, s in chosen.items() if s is not None}, {}


class ScanInbox:
    """The fleet's sonar scans heard since the last step (drained from a ring once a
    step; the robot's own never taken: it adds its own as it reads them).
    """

    def __init__(self, robot_id: str, formation: Formation, *, fleet: str) -> None:
        self.robot_id, self.formation, self.fleet = robot_id, formation, fleet
        self.heard = 0  # scans taken from the other robots
        self._ring: Polled[ScanMessage] | None = None
        self._waiting: list[Scan] = []

    def attach(self, session: FleetSession, bounds: FleetBounds | None) -> None:
        """Subscribe to every robot's scans."""
        capacity = RING_PER_ROBOT * len(self.formation.robot_ids)
        self._ring = session.subscribe_polled(
            robots_key(self.fleet, "scan"), ScanMessage, capacity, context=bounds
        )

    def take(self) -> tuple[Scan, ...]:
        """The scans heard since the last call, oldest first."""
        if self._ring is not None:
            self._ring.drain(self._on_scan)
        taken, self._waiting = tuple(self._waiting), []
        self.heard += len(taken)
        return taken

    def _on_scan(self, _key: str, message: ScanMessage) -> None:
        if message.robot_id != self.robot_id:
            self._waiting.append(message.scan())
