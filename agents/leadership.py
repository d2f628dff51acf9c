"""Leadership over shared state: who leads the formation, under which epoch, and which
robot each robot tracks. Every robot runs this on the same inputs (every robot's flags of
the same control step) and so reaches the same decision on its own; nothing is negotiated.

The rules:

1. **Epochs.** Every robot holds `(leader, epoch)`, starting at `(formation root, 0)`.
   Epochs only grow, by one a change (saturating at the top of their 32-bit range,
   `phalanx.core.peers.next_epoch`); a lower epoch is ignored, so a late or replayed
   message can never hand leadership back. (One exception: a robot alone in its pair,
   which every other live robot, the leader they name heard among them, has not
   followed `timeout_s + loss_grace_s` after the change, takes theirs back; it changed
   on flags they did not show, and two robots would otherwise lead for good.) A peer's
   pair is adopted only when the fleet stands behind it (`Leadership.verdict`), never on
   one robot's word:
   - the next epoch, naming the leader rules 2 or 3 would choose from this robot's own
     view: the current leader gone from it, or handing over (its flags call for it) to
     the best robot that can take over; or the pair the leader's own flags name, to a
     robot that can take over or has (the leader chose on the flags of its step);
   - or a pair held by more than half the live robots (a robot that missed a change
     catches up);
   - or, within `timeout_s + loss_grace_s` of a change, the same epoch held by as many
     robots, claimed by the leader it names for itself, that leader better by rule 4
     than this robot's, which, if heard, claims the lead for itself too or holds that
     pair already (two robots that decided on different flags converge).
   Anything else is refused and kept in `refusals` for the runtime to count: a stolen
   robot identity can stop its own robot, not move the lead. A restarted robot
   (`joining`) takes, for `timeout_s` after it first hears the fleet, the pair most of
   the other robots hold.
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

from collections import Counter, deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

from phalanx.core.config import LeadershipConfig
from phalanx.core.formation import Formation
from phalanx.core.peers import next_epoch
from phalanx.core.states import OUT_OF_FORMATION, State


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
    @property
    def settled(self) -> bool: ...  # noqa: D102


Flags = Mapping[str, FlagsView]
_EPS_S = 1e-9
# Only a robot actually following its plan may hand leadership over.
_HANDING_STATES = frozenset({State.NAVIGATE, State.WANDER})
_CANDIDATE_STATES = frozenset({State.FORMATION_TRACK, State.FORMATION_REVERSE})
# A deadlock is a leader stuck while going forwards (its flags then say what lies ahead).
_DEADLOCK_FROM = _HANDING_STATES | {State.EMERGENCY_STOP}
_BUSY_STATES = OUT_OF_FORMATION | {State.HOLD}
# Refused claims kept for the runtime to count (a step's worth; the batch runner reads none).
REFUSALS_KEPT = 64
Claim = tuple[int, str]  # (epoch, leader)


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


@dataclass(frozen=True, slots=True)
class RefusedClaim:
    """A peer's `(epoch, leader)` claim not adopted: whose flags (stamped when, s) said
    what, and why it was refused.
    """

    robot_id: str
    epoch: int
    leader_id: str
    stamp_s: float
    why: str

    def describe(self) -> str:
        """One line for a log or a counter's last error."""
        return f"{self.robot_id} claims {self.leader_id} under epoch {self.epoch}: {self.why}"


class LiveFlags(dict[str, FlagsView]):
    """The flags of the robots heard lately, with the group-wide summaries every robot
    asks of them worked out once: robots stepped in one process (the batch runner) share
    one per control step, so a step costs each of them O(1) in the group's size, not O(n).
    """

    claims: dict[Claim, int]  # how many robots heard name each (epoch, leader) of the formation
    stopped: frozenset[str]  # the robots in an emergency stop
    stopped_behind: frozenset[str]  # ... that they came to backwards: for what lies behind
    busy: frozenset[str]  # the robots out of formation or holding still

    def __init__(
        self,
        flags: Mapping[str, FlagsView] | Iterable[tuple[str, FlagsView]],
        formation: Formation,
    ) -> None:
        super().__init__(flags)
        self.formation = formation
        # What every robot's step reads, in one pass over the flags.
        rank = formation.rank
        claims: dict[Claim, int] = {}
        stopped, behind, busy = [], [], []
        for r, f in self.items():
            if f.formation_leader_id in rank:
                claim = (f.epoch, f.formation_leader_id)
                claims[claim] = claims.get(claim, 0) + 1
            if f.fsm_state == State.EMERGENCY_STOP:
                stopped.append(r)
                if f.direction < 0:
                    behind.append(r)
            if f.fsm_state in _BUSY_STATES:
                busy.append(r)
        self.claims = claims
        self.stopped, self.stopped_behind = frozenset(stopped), frozenset(behind)
        self.busy = frozenset(busy)

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


def successor(formation: Formation, live: Flags, gone: str, robot_id: str) -> str | None:
    """Rule 3's choice when leader `gone` is lost, as robot `robot_id` sees it: the best
    live robot but `gone`, not joining (`robot_id` itself counts, heard or not).
    """
    alive = {r: f for r, f in live.items() if r != gone and f.fsm_state != State.JOIN}
    return best(formation, alive, () if robot_id in alive else (robot_id,))


def _pair(flags: FlagsView) -> Claim:
    """The `(epoch, leader)` a robot's flags hold."""
    return flags.epoch, flags.formation_leader_id


def _may_take(flags: FlagsView | None, epoch: int, leader: str) -> bool:
    """Whether the robot of `flags` may take the lead a leader hands it under `epoch`:
    it can lead, or has taken it already.
    """
    if flags is None:
        return False
    return can_lead(flags) or _pair(flags) == (epoch, leader)


def taker(formation: Formation, live: Flags, leader: str) -> str | None:
    """Rule 2's choice to take over from `leader`: the best follower that can lead."""
    return best(formation, {r: f for r, f in live.items() if r != leader and can_lead(f)})


class Leadership:
    """One robot's view of the leadership, updated from every robot's flags."""

    def __init__(
        self,
        robot_id: str,
        formation: Formation,
        config: LeadershipConfig,
        *,
        timeout_s: float,
        joining: bool = False,
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
        self.joining = joining  # restarted: takes the pair most of the fleet holds
        self.join_heard_s: float | None = None  # when a joining robot first heard another
        self.refused = 0  # peers' flags whose claim was refused, so far
        self.refusals: deque[RefusedClaim] = deque(maxlen=REFUSALS_KEPT)  # newest, for a runtime
        self._counted: dict[str, float] = {}  # robot -> stamp of its flags last refused
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
        """Adopt the best claim the fleet stands behind (rule 1); count the others."""
        if self.joining:
            return self._join(live, t_s)
        mine = (self.epoch, self.leader_id)
        claims = live.claims
        if len(claims) == 1 and mine in claims:
            return None  # everyone agrees: the common case, O(1)
        taken: list[tuple[Claim, str]] = []
        for claim in claims:
            if claim != mine:
                adopt, why = self.verdict(claim, live, t_s)
                if adopt:
                    taken.append((claim, why))
                elif why:
                    self._refuse(claim, why, live)
        if not taken:
            return None
        rank = self.formation.rank

        def order(taken: tuple[Claim, str]) -> tuple[int, int, int]:
            (epoch, leader), _ = taken  # the newest epoch, then the most held, then rank
            return (epoch, self._votes((epoch, leader), live)[0], -rank[leader])

        (epoch, leader), why = max(taken, key=order)
        return self._set(leader, epoch, t_s, why)

    def verdict(self, claim: Claim, live: LiveFlags, t_s: float) -> tuple[bool, str]:
        """Whether to adopt a peer's `claim` (rule 1), and why; refused with no reason:
        old news, or a split still settling.
        """
        epoch, leader = claim
        held, voters = self._votes(claim, live)
        if epoch < self.epoch:
            return self._step_back(claim, held, voters, live, t_s)
        if 2 * held > voters:
            return True, f"held by {held} of {voters} live robots"
        if epoch == self.epoch:
            return self._split(claim, held, live, t_s)
        if epoch != next_epoch(self.epoch):
            return False, f"epoch {epoch} jumps from {self.epoch}"
        why = self._unjustified(leader, epoch, live)
        return (False, why) if why else (True, f"epoch {epoch}: {leader} is the rule's choice")

    def _split(self, claim: Claim, held: int, live: LiveFlags, t_s: float) -> tuple[bool, str]:
        """A claim at this robot's epoch naming another leader: two robots that decided
        on different flags. Within `timeout_s + loss_grace_s` of the change, a leader that
        claims the lead itself, held by as many robots as this robot's and better than it
        by rule 4 (the two compared on their flags as heard: every robot compares alike),
        is adopted, if this robot's leader, heard, claims the lead itself too or holds
        `claim` already (else there are not two claims to settle: a robot that named this
        one's leader and then itself at the same epoch moves nobody); later only a
        majority moves the lead.
        """
        epoch, leader = claim
        if t_s - self.since_s > self.timeout_s + self.config.loss_grace_s + _EPS_S:
            return False, f"epoch {epoch} is {self.leader_id}'s"
        flags = live.get(leader)
        if flags is None or _pair(flags) != claim:
            return False, ""  # (a robot a step behind the two claimants: no vote of its own)
        ours = None if self.is_leader else live.get(self.leader_id)  # (own flags: a step old)
        if ours is not None and _pair(ours) not in ((epoch, ours.robot_id), claim):
            return False, ""  # (this robot's leader neither claims the lead nor follows `claim`)
        pair = {r: f for r, f in live.items() if r in (leader, self.leader_id)}
        unheard = () if self.leader_id in pair else (self.leader_id,)
        better = best(self.formation, pair, unheard) == leader
        mine = (self.epoch, self.leader_id)
        return better and held >= self._votes(mine, live)[0], ""

    def _step_back(
        self, claim: Claim, held: int, voters: int, live: LiveFlags, t_s: float
    ) -> tuple[bool, str]:
        """An older epoch than this robot's: old news, unless this robot alone holds its
        pair and every other live robot, the leader `claim` names among them, still holds
        `claim` `timeout_s + loss_grace_s` after the change: a change the fleet did not
        follow (one robot took the lead on flags the others no longer showed, such as its
        own path clear a step before its sonar saw the obstacle the others saw). It goes
        back to the fleet's pair, rather than leave two leaders for good. A leader this
        robot does not hear is no pair to go back to: cut off from it, the robot keeps
        what rule 3 made of that.
        """
        alone = self._votes((self.epoch, self.leader_id), live)[0] == 1
        others = voters - 1
        lead = live.get(claim[1])
        leads = lead is not None and _pair(lead) == claim
        settled_s = self.timeout_s + self.config.loss_grace_s + _EPS_S
        if not (alone and leads and others and held >= others) or t_s - self.since_s <= settled_s:
            return False, ""
        return True, (
            f"epoch {self.epoch} not followed: epoch {claim[0]} held by the {held} other "
            "live robots"
        )

    def _unjustified(self, leader: str, epoch: int, live: LiveFlags) -> str:
        """Why the rule would not pass the lead to `leader` now ("" if it would). A
        leader whose own flags hand the lead to `leader` is followed if `leader` can lead
        or has taken it, whether or not this robot's view would pick it: the leader chose
        on its flags of that step, which this robot's may no longer match (else the two
        would part for good, each refusing the other's pair).
        """
        lead = live.get(self.leader_id)
        if lead is None:
            choice = successor(self.formation, live, self.leader_id, self.robot_id)
            gone = f"{self.leader_id} is gone"
        else:
            handing = _pair(lead) == (epoch, leader)
            if handing and leader != self.leader_id and _may_take(live.get(leader), epoch, leader):
                return ""
            if not handing and not self._calls_for_handover(lead, live):
                return f"{self.leader_id} leads and is not handing over"
            choice = taker(self.formation, live, self.leader_id)
            gone = f"{self.leader_id} hands over"
        return "" if leader == choice else f"{gone}: the rule picks {choice}, not {leader}"

    def _votes(self, claim: Claim, live: LiveFlags) -> tuple[int, int]:
        """How many live robots hold `claim` (this one by its current pair, not by its
        flags, which may be a step old), of how many.
        """
        own = live.get(self.robot_id)
        held = live.claims.get(claim, 0) + (claim == (self.epoch, self.leader_id))
        if own is not None and _pair(own) == claim:
            held -= 1
        return held, len(live) + (own is None)

    def _join(self, live: LiveFlags, t_s: float) -> LeadershipChange | None:
        """A restarted robot: the pair most of the other live robots hold (ties: newer)."""
        others = Counter(live.claims)
        own = live.get(self.robot_id)
        if own is not None:
            others[_pair(own)] -= 1
        others = +others
        if not others:
            return None
        if self.join_heard_s is None:
            self.join_heard_s = t_s
        self.joining = t_s - self.join_heard_s < self.timeout_s
        rank = self.formation.rank
        claim = max(others, key=lambda c: (others[c], c[0], -rank[c[1]]))
        if claim == (self.epoch, self.leader_id):
            return None
        return self._set(claim[1], claim[0], t_s, "the fleet's leader, heard on joining")

    def _refuse(self, claim: Claim, why: str, live: LiveFlags) -> None:
        """Keep (once per message) the flags that made `claim` for the runtime to count."""
        for robot, flags in live.items():
            said = _pair(flags) == claim
            if said and robot != self.robot_id and self._counted.get(robot) != flags.stamp_s:
                self._counted[robot] = flags.stamp_s
                self.refused += 1
                self.refusals.append(RefusedClaim(robot, claim[0], claim[1], flags.stamp_s, why))

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
        chosen = successor(self.formation, live, self.leader_id, self.robot_id)
        if chosen is None:
            return None
        why = f"leader {self.leader_id} silent for {silent_s:.1f} s"
        return self._set(chosen, next_epoch(self.epoch), t_s, why)

    def _calls_for_handover(self, lead: FlagsView, live: LiveFlags) -> bool:
        """Whether the leader's flags call for rule 2 (its tenure aside)."""
        return (
            self.config.handover
            and lead.obstacle
            and lead.blocked_s >= self.config.confirm_s - _EPS_S
            and lead.fsm_state in _HANDING_STATES
            and not lead.dead_end
            and not live.all_blocked
        )

    def _handover(self, live: LiveFlags, t_s: float) -> LeadershipChange | None:
        lead = live.get(self.leader_id)
        if (
            lead is None
            or t_s - self.since_s < self.config.min_tenure_s - _EPS_S
            or not self._calls_for_handover(lead, live)
        ):
            return None
        chosen = taker(self.formation, live, self.leader_id)
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
