"""Leadership over shared state: who leads the formation, under which epoch, and which
robot each robot tracks. Every robot runs this on the same inputs (every robot's flags of
the same control step) and so reaches the same decision on its own; nothing is negotiated.

The rules:

1. **Epochs.** Every robot holds `(leader, epoch)`, starting at `(formation root, 0)`. It
   adopts a peer's pair when that is newer: a higher epoch, or the same epoch with a
   leader earlier in the formation's order (two robots that decided on different flags
   converge in one step). A lower epoch is ignored, so a late or replayed message can
   never hand leadership back. Epochs only grow (and saturate at the top of their
   32-bit range, `phalanx.core.peers.next_epoch`).
2. **Handover.** When the leader's flags say its path has been blocked for `confirm_s`,
   not every robot is blocked (that is the deadlock, the leader's to handle), nor is
   the leader in a dead end (its route leads back: a new leader would face the same),
   the leader is navigating (not reversing or stopped) and has led for `min_tenure_s`,
   and some follower in formation is clear: the best clear follower leads, epoch + 1.
3. **Loss.** When the leader's flags are missing (its process is gone) or stale, the
   followers hold; `loss_grace_s` after the leader's last flags went stale, the best live
   robot leads under epoch + 1. A robot never declares itself lost.
4. **Best** = clear before not clear, then the slot furthest forward in the formation's
   shape, then the formation's order: a total order, the same on every robot.
5. **Tracking tree.** The configured follow tree re-rooted at the leader: each robot
   tracks its neighbour on the tree path to the leader, or, when that one is gone or out
   of formation (avoiding, stopped, rejoining), the next one along the path, the leader
   at last. (l, phi) to whichever robot it tracks come from the shape (`slot_of`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

from phalanx.core.config import LeadershipConfig
from phalanx.core.formation import Formation
from phalanx.core.peers import next_epoch
from phalanx.core.states import DEADLOCK_STATES, OUT_OF_FORMATION, State


class FlagsView(Protocol):
    """What leadership reads of a robot: a `RobotFlags`, or a `RobotState` (a superset)."""

    @property
    def robot_id(self) -> str: ...  # noqa: D102
    @property
    def stamp_s(self) -> float: ...  # noqa: D102
    @property
    def fsm_state(self) -> str: ...  # noqa: D102
    @property
    def obstacle(self) -> bool: ...  # noqa: D102
    @property
    def direction(self) -> int: ...  # noqa: D102
    @property
    def blocked_s(self) -> float: ...  # noqa: D102
    @property
    def dead_end(self) -> bool: ...  # noqa: D102
    @property
    def clear(self) -> bool: ...  # noqa: D102
    @property
    def formed(self) -> bool: ...  # noqa: D102
    @property
    def epoch(self) -> int: ...  # noqa: D102
    @property
    def formation_leader_id(self) -> str: ...  # noqa: D102
    @property
    def waypoint(self) -> int: ...  # noqa: D102
    @property
    def deadlocks(self) -> int: ...  # noqa: D102
    @property
    def profile_s(self) -> float: ...  # noqa: D102
    @property
    def shape_source(self) -> int: ...  # noqa: D102
    @property
    def shape_target(self) -> int: ...  # noqa: D102
    @property
    def morph(self) -> float: ...  # noqa: D102


Flags = Mapping[str, FlagsView]
_EPS_S = 1e-9
# Only a robot actually following its plan may hand leadership over.
_HANDING_STATES = frozenset({State.NAVIGATE, State.WANDER})
_CANDIDATE_STATES = frozenset({State.FORMATION_TRACK, State.FORMATION_REVERSE})
# A deadlock is a leader stuck while going forwards (its flags then say what lies ahead).
_DEADLOCK_FROM = _HANDING_STATES | {State.EMERGENCY_STOP}
_BUSY_STATES = OUT_OF_FORMATION | {State.HOLD}


@dataclass(frozen=True, slots=True)
class LeadershipChange:
    """A change of leader: when (s), from whom, to whom, under which epoch, why."""

    t_s: float
    previous_id: str
    leader_id: str
    epoch: int
    reason: str


def newer(a: tuple[int, str], b: tuple[int, str], formation: Formation) -> bool:
    """Whether `(epoch, leader)` pair `a` supersedes `b` (rule 1)."""
    rank = formation.rank
    if a[1] not in rank:
        return False
    return (a[0], -rank[a[1]]) > (b[0], -rank.get(b[1], len(rank)))


class LiveFlags(dict[str, FlagsView]):
    """The flags of the robots heard lately, with the group-wide summaries every robot
    asks of them worked out once: robots stepped in one process (the batch runner) share
    one per control step, so a step costs each of them O(1) in the group's size, not O(n).
    """

    def __init__(
        self,
        flags: Mapping[str, FlagsView] | Iterable[tuple[str, FlagsView]],
        formation: Formation,
    ) -> None:
        super().__init__(flags)
        self.formation = formation

    @cached_property
    def newest(self) -> tuple[int, str] | None:
        """The newest `(epoch, leader)` claim among the flags (rule 1), None if none."""
        rank = self.formation.rank
        claims = [(f.epoch, f.formation_leader_id) for f in self.values()]
        valid = [c for c in claims if c[1] in rank]
        return max(valid, key=lambda c: (c[0], -rank[c[1]])) if valid else None

    @cached_property
    def all_blocked(self) -> bool:
        """Whether every robot heard reports an obstacle on its path."""
        return all(f.obstacle for f in self.values())

    @cached_property
    def stopped(self) -> frozenset[str]:
        """The robots in an emergency stop."""
        return frozenset(r for r, f in self.items() if f.fsm_state == State.EMERGENCY_STOP)

    @cached_property
    def stopped_behind(self) -> frozenset[str]:
        """The robots in an emergency stop they came to backwards: for what lies behind."""
        return frozenset(r for r in self.stopped if self[r].direction < 0)

    @cached_property
    def busy(self) -> frozenset[str]:
        """The robots out of formation or holding still."""
        return frozenset(r for r, f in self.items() if f.fsm_state in _BUSY_STATES)


class _LastLive:
    """The last `LiveFlags` built, kept for the next robot of the same step to reuse: same
    flags object (a step's mapping, never changed once handed out), time, formation and
    timeout give the same live flags. One tuple, swapped whole: threads running separate
    fleets never see one fleet's key with another's flags.
    """

    entry: tuple[object, float, object, float, LiveFlags] | None = None


def best(formation: Formation, candidates: Flags, others: tuple[str, ...] = ()) -> str | None:
    """The best of `candidates` (by their flags) and `others` (no flags: not clear)."""
    order = formation.robot_ids

    def key(robot: str) -> tuple[int, float, int]:
        flags = candidates.get(robot)
        clear = flags is not None and flags.clear
        return (0 if clear else 1, -formation.positions[robot].x_m, order.index(robot))

    pool = [r for r in (*candidates, *others) if r in formation.positions]
    return min(pool, key=key) if pool else None


def can_lead(flags: FlagsView) -> bool:
    """Whether a follower may take over from a blocked leader: in formation, path clear."""
    return flags.clear and flags.formed and flags.fsm_state in _CANDIDATE_STATES


class Leadership:
    """One robot's view of the leadership, updated from every robot's flags."""

    def __init__(
        self,
        robot_id: str,
        formation: Formation,
        config: LeadershipConfig,
        *,
        timeout_s: float,
    ) -> None:
        self.robot_id = robot_id
        self.formation = formation
        self.config = config
        self.timeout_s = timeout_s
        self.leader_id = formation.root
        self.epoch = 0
        self.since_s = 0.0
        self.leader_heard_s = 0.0
        self.changes: list[LeadershipChange] = []
        self._paths: dict[tuple[str, str], tuple[str, ...]] = {}

    @property
    def is_leader(self) -> bool:
        """Whether this robot leads the formation."""
        return self.leader_id == self.robot_id

    def live(self, flags: Flags, t_s: float) -> LiveFlags:
        """The flags of robots of this formation heard within `timeout_s` of `t_s`."""
        last = _LastLive.entry
        if (
            last is not None
            and last[0] is flags
            and last[1] == t_s
            and last[2] is self.formation
            and last[3] == self.timeout_s
        ):
            return last[4]
        positions = self.formation.positions
        live = LiveFlags(
            (
                (r, f)
                for r, f in flags.items()
                if r in positions and t_s - f.stamp_s <= self.timeout_s + _EPS_S
            ),
            self.formation,
        )
        _LastLive.entry = (flags, t_s, self.formation, self.timeout_s, live)
        return live

    def update(self, live: Flags, t_s: float) -> LeadershipChange | None:
        """Adopt newer epochs, then apply the loss and handover rules; the change, if any."""
        if not isinstance(live, LiveFlags):
            live = LiveFlags(live, self.formation)
        adopted = self._adopt(live, t_s)
        if self.leader_id in live:
            self.leader_heard_s = max(self.leader_heard_s, live[self.leader_id].stamp_s)
        decided = self._lost(live, t_s) or self._handover(live, t_s)
        return decided or adopted

    def leader_lost(self, live: Flags) -> bool:
        """Whether the leader is gone from this robot's view (followers hold)."""
        return not self.is_leader and self.leader_id not in live

    def _adopt(self, live: LiveFlags, t_s: float) -> LeadershipChange | None:
        newest = live.newest
        if newest is None or not newer(newest, (self.epoch, self.leader_id), self.formation):
            return None
        return self._set(newest[1], newest[0], t_s, "newer epoch heard")

    def _set(self, leader: str, epoch: int, t_s: float, reason: str) -> LeadershipChange:
        change = LeadershipChange(t_s, self.leader_id, leader, epoch, reason)
        self.leader_id, self.epoch, self.since_s = leader, epoch, t_s
        self.leader_heard_s = t_s  # a new leader gets the full grace before it is lost
        self.changes.append(change)
        return change

    def _lost(self, live: Flags, t_s: float) -> LeadershipChange | None:
        if not self.leader_lost(live):
            return None
        silent_s = t_s - self.leader_heard_s
        if silent_s <= self.timeout_s + self.config.loss_grace_s + _EPS_S:
            return None
        alive = {r: f for r, f in live.items() if r != self.leader_id and f.fsm_state != State.JOIN}
        others = () if self.robot_id in alive else (self.robot_id,)
        chosen = best(self.formation, alive, others)
        if chosen is None:
            return None
        why = f"leader {self.leader_id} silent for {silent_s:.1f} s"
        return self._set(chosen, next_epoch(self.epoch), t_s, why)

    def _handover(self, live: LiveFlags, t_s: float) -> LeadershipChange | None:
        lead = live.get(self.leader_id)
        if (
            not self.config.handover
            or lead is None
            or not lead.obstacle
            or lead.blocked_s < self.config.confirm_s - _EPS_S
            or lead.fsm_state not in _HANDING_STATES
            or lead.dead_end
            or t_s - self.since_s < self.config.min_tenure_s - _EPS_S
            or live.all_blocked
        ):
            return None
        clear = {r: f for r, f in live.items() if r != self.leader_id and can_lead(f)}
        chosen = best(self.formation, clear)
        if chosen is None:
            return None
        why = f"{self.leader_id} blocked for {lead.blocked_s:.1f} s, {chosen} clear"
        return self._set(chosen, next_epoch(self.epoch), t_s, why)

    def path(self, robot: str) -> tuple[str, ...]:
        """The tree path from `robot` to the leader (leader included)."""
        key = (robot, self.leader_id)
        if key not in self._paths:
            self._paths[key] = self.formation.tree_path(robot, self.leader_id)
        return self._paths[key]

    def tracked(self, live: Flags) -> str | None:
        """Whom this robot tracks (rule 5), None for the leader."""
        if self.is_leader:
            return None
        for robot in self.path(self.robot_id):
            flags = live.get(robot)
            usable = flags is not None and flags.formed and flags.fsm_state not in OUT_OF_FORMATION
            if robot == self.leader_id or usable:
                return robot
        return self.leader_id


def group_deadlock(
    live: Flags,
    leader_id: str,
    *,
    confirm_s: float,
    widened: bool = True,
    queued: Mapping[str, str] | None = None,
) -> str:
    """Why the group is in deadlock (rule of the paper, widened), or "" if it is not.

    Every robot blocked (the paper: "all the robots experience obstacles on their path at
    the same time"); or, `widened`, the leader blocked for `confirm_s` with no follower
    clear to take over (the paper: "the confusion in lending their leadership").

    `queued` (the paper's rule alone): each robot whose slot is straight behind another's
    (a column), with that robot. Its path is that robot's: when that robot is blocked, so
    is it, though its sonar cannot see past it to what blocks it.
    """
    lead = live.get(leader_id)
    if lead is None or not lead.obstacle or lead.fsm_state not in _DEADLOCK_FROM:
        return ""
    ahead = {} if widened else dict(queued or {})
    if all(_blocked(r, live, ahead) for r in live):
        return f"every robot blocked ({', '.join(sorted(live))})"
    clear = [r for r, f in live.items() if r != leader_id and can_lead(f)]
    if widened and lead.blocked_s >= confirm_s - _EPS_S and lead.dead_end:
        return f"{leader_id} in a dead end: its route leads back and the shape cannot turn"
    if widened and lead.blocked_s >= confirm_s - _EPS_S and not clear:
        return f"{leader_id} blocked for {lead.blocked_s:.1f} s and no robot clear"
    return ""


def _blocked(robot: str, live: Flags, ahead: Mapping[str, str]) -> bool:
    """Whether `robot` is blocked, or queues behind a robot that is (up its column)."""
    seen = set()
    while robot not in seen:
        flags = live.get(robot)
        if flags is not None and flags.obstacle:
            return True
        seen.add(robot)
        if robot not in ahead:
            return False
        robot = ahead[robot]
    return False


def in_deadlock_escape(live: Flags, leader_id: str) -> bool:
    """Whether the leader's flags show it backing off or turning away."""
    lead = live.get(leader_id)
    return lead is not None and lead.fsm_state in DEADLOCK_STATES
