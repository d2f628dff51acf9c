"""The layered behaviour stack of one robot as one explicit state machine: the navigation
layer (the leader's plan, the deadlock escape, reactive avoidance and the emergency stop
on every robot) over the formation layer (a follower tracking or reversing with the robot
it follows), arbitrated by priority (the paper's figure 1, section 3).

Leadership can pass to any robot, so every robot carries both layers; its role (leader
or follower, decided by `phalanx.agents.leadership`) is an input of the guards. The
arbitration table, `ARBITRATION`, is the written form of the transition priorities: a
higher row wins whenever its condition holds, whatever lower row is active.

The context is refreshed by the agent core every step; guards only read it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from phalanx.agents.fsm import ANY_STATE, StateMachine, Transition
from phalanx.core.states import State

Plan = Literal["scripted", "goto", "wander"]


@dataclass(frozen=True)
class Rule:
    """One row of the arbitration table."""

    priority: int
    behaviour: str
    layer: str
    role: str
    when: str


# Priorities of the transitions below; a row wins over every row beneath it.
P_STUCK = 100
P_BEHIND = 95
P_ESTOP = 90
P_ROLE = 80
P_HOLD = 70
P_GIVE_UP = 65
P_DEADLOCK = 60
P_AVOID = 40
P_DIRECTION = 30
P_ARRIVE = 20
P_RESUME = 10

ARBITRATION: tuple[Rule, ...] = (
    Rule(P_STUCK, "STUCK", "navigation", "any",
         "deadlock retries used up at this waypoint (or the leader is STUCK): stop for good"),
    Rule(P_BEHIND, "DEADLOCK_TURN", "navigation", "leader",
         "reversing and an obstacle is behind (or a robot stopped for one): stop reversing"),
    Rule(P_ESTOP, "EMERGENCY_STOP", "navigation", "any",
         "bumper, or an obstacle within braking distance + margin in the direction of motion"),
    Rule(P_ROLE, "NAVIGATE / FORMATION_TRACK", "leadership", "any",
         "leadership passed to or from this robot (handover, leader lost, newer epoch)"),
    Rule(P_HOLD, "HOLD", "formation", "follower",
         "the formation leader or the tracked robot is gone or its state is stale"),
    Rule(P_DEADLOCK, "DEADLOCK_REVERSE", "navigation", "leader",
         "deadlock: every robot blocked, or the leader blocked and nobody clear to lead"),
    Rule(P_AVOID, "AVOID", "navigation", "follower",
         "own path blocked while the leader's is not: leave the slot, go round, come back"),
    Rule(P_DIRECTION, "FORMATION_REVERSE / FORMATION_TRACK", "formation", "follower",
         "the tracked robot moves backwards / forwards (the paper's switch, figure 4a)"),
    Rule(P_ARRIVE, "ARRIVED", "navigation", "leader", "the last waypoint is reached"),
    Rule(P_RESUME, "NAVIGATE / WANDER", "navigation", "leader",
         "default: go to the next waypoint (or run the script), or wander without one"),
)  # fmt: skip

LEADER_STATES = frozenset(
    {State.NAVIGATE, State.WANDER, State.ARRIVED, State.DEADLOCK_REVERSE, State.DEADLOCK_TURN}
)
FOLLOWER_STATES = frozenset(
    {State.FORMATION_TRACK, State.FORMATION_REVERSE, State.AVOID, State.HOLD}
)
# A robot in one of these has left its slot: nobody may track it (leadership.tracked).
OUT_OF_FORMATION = frozenset({State.AVOID, State.EMERGENCY_STOP, State.JOIN, State.STUCK})
DEADLOCK_STATES = frozenset({State.DEADLOCK_REVERSE, State.DEADLOCK_TURN})


@dataclass
class StackContext:
    """What the guards read; the agent core refreshes it before every update."""

    # role and plan
    is_leader: bool = False
    plan: Plan = "scripted"
    arrived: bool = False
    role_reason: str = ""
    joined: bool = True
    reactive: bool = True  # avoidance and emergency stop on
    # own sensing this step
    bumper: bool = False
    imminent: bool = False
    standstill: bool = True
    way_clear: bool = True  # nothing within braking range the way the robot is meant to go
    blocked_s: float = 0.0
    way_free_s: float = 0.0  # AVOID: how long the way back to the slot has been free
    # the group, from every robot's flags
    leader_lost: bool = False
    leader_blocked: bool = False
    leader_state: str = ""
    parent_fresh: bool = False
    parent_v_mps: float = 0.0
    parent_direction: int = 1
    deadlock: bool = False
    deadlock_reason: str = ""
    someone_stopped: bool = False
    retries_left: bool = True
    stuck_reason: str = ""
    # deadlock escape progress
    reversed_m: float = 0.0
    safe_distance_m: float = 1.5
    path_used_up: bool = False  # backed along all of the recorded path
    turned: bool = False
    # tunables the guards need
    confirm_s: float = 0.2
    threshold_mps: float = 0.02

    @property
    def follower(self) -> bool:
        """Not the leader."""
        return not self.is_leader

    @property
    def reversing(self) -> bool:
        """The tracked robot moves backwards (beyond the hysteresis band)."""
        return self.parent_fresh and self.parent_v_mps < -self.threshold_mps

    @property
    def forwards(self) -> bool:
        """The tracked robot moves forwards (beyond the hysteresis band)."""
        return self.parent_fresh and self.parent_v_mps > self.threshold_mps

    @property
    def lost(self) -> bool:
        """A follower with nobody to track."""
        return self.leader_lost or not self.parent_fresh


Guard = Callable[[StackContext], bool]


def _leads(plan: Plan | None, arrived: bool | None = None) -> Guard:
    def guard(c: StackContext) -> bool:
        return (
            c.is_leader
            and (plan is None or (c.plan == "wander") == (plan == "wander"))
            and (arrived is None or c.arrived == arrived)
        )

    return guard


def _both(a: Guard, b: Guard) -> Guard:
    def guard(c: StackContext) -> bool:
        return a(c) and b(c)

    return guard


def _role_reason(c: StackContext) -> str:
    return c.role_reason


def _leader_targets(
    sources: tuple[str, ...],
    guard: Guard,
    reason: str,
    priority: int,
    *,
    role_change: bool = False,
) -> list[Transition[StackContext]]:
    """`sources` -> the leader state the plan calls for, when `guard` also holds."""
    targets: list[tuple[str, Guard]] = [
        (State.ARRIVED, _leads(None, arrived=True)),
        (State.WANDER, _leads("wander", arrived=False)),
        (State.NAVIGATE, _leads("goto", arrived=False)),
    ]
    return [
        Transition(
            s,
            target,
            _both(plan, guard),
            reason,
            priority,
            detail=_role_reason if role_change else None,
        )
        for s in sources
        for target, plan in targets
        if s != target
    ]


def _role_transitions() -> list[Transition[StackContext]]:
    followers = (State.FORMATION_TRACK, State.FORMATION_REVERSE, State.AVOID, State.HOLD)
    leaders = tuple(LEADER_STATES)
    took = _leader_targets(followers, lambda c: True, "took the lead", P_ROLE, role_change=True)
    gave: list[Transition[StackContext]] = [
        Transition(
            s,
            State.FORMATION_TRACK,
            lambda c: c.follower,
            "handed the lead on",
            P_ROLE,
            detail=_role_reason,
        )
        for s in sorted(leaders)
    ]
    joined = _leader_targets(
        (State.JOIN,), lambda c: c.joined, "joined the fleet", P_RESUME, role_change=True
    )
    joined.append(
        Transition(
            State.JOIN,
            State.FORMATION_TRACK,
            lambda c: c.joined and c.follower,
            "joined the fleet",
            P_RESUME,
            detail=_role_reason,
        )
    )
    return took + gave + joined


def _safety_transitions() -> list[Transition[StackContext]]:
    stopped = "came to a standstill"
    return [
        Transition(
            ANY_STATE,
            State.STUCK,
            lambda c: c.follower and c.leader_state == State.STUCK,
            "the formation leader is STUCK",
            P_STUCK,
        ),
        Transition(
            ANY_STATE,
            State.EMERGENCY_STOP,
            lambda c: c.reactive and (c.bumper or c.imminent) and c.joined,
            "bumper pressed or an obstacle inside the braking distance",
            P_ESTOP,
        ),
        Transition(
            State.EMERGENCY_STOP,
            State.AVOID,
            lambda c: (
                c.reactive and c.follower and c.standstill and c.blocked_s > 0.0 and not c.reversing
            ),
            f"{stopped}, way ahead blocked: going round",
            P_AVOID,
        ),
        Transition(
            State.EMERGENCY_STOP,
            State.FORMATION_TRACK,
            lambda c: c.follower and c.standstill and c.way_clear and not c.bumper,
            f"{stopped}, way clear: back to the formation",
            P_RESUME,
        ),
        *_leader_targets(
            (State.EMERGENCY_STOP,),
            lambda c: c.standstill and c.way_clear and not c.bumper,
            f"{stopped}, way clear: back to the plan",
            P_RESUME,
        ),
    ]


def _formation_transitions() -> list[Transition[StackContext]]:
    lost = "leader or tracked robot missing or stale"
    hold: list[Transition[StackContext]] = [
        Transition(s, State.HOLD, lambda c: c.follower and c.lost, lost, P_HOLD)
        for s in (State.FORMATION_TRACK, State.FORMATION_REVERSE, State.AVOID)
    ]
    return [
        *hold,
        Transition(
            State.HOLD,
            State.FORMATION_REVERSE,
            lambda c: c.follower and not c.lost and c.parent_direction < 0,
            "leader heard again, moving backwards",
            P_RESUME,
        ),
        Transition(
            State.HOLD,
            State.FORMATION_TRACK,
            lambda c: c.follower and not c.lost and c.parent_direction > 0,
            "leader heard again",
            P_RESUME,
        ),
        Transition(
            State.FORMATION_TRACK,
            State.FORMATION_REVERSE,
            lambda c: c.follower and c.reversing,
            "tracked robot moves backwards (v < -threshold)",
            P_DIRECTION,
        ),
        Transition(
            State.FORMATION_REVERSE,
            State.FORMATION_TRACK,
            lambda c: c.follower and c.forwards,
            "tracked robot moves forwards (v > threshold)",
            P_DIRECTION,
        ),
        Transition(
            State.FORMATION_TRACK,
            State.AVOID,
            _should_avoid,
            "own path blocked while the leader's is clear",
            P_AVOID,
            detail=lambda c: f"blocked for {c.blocked_s:.1f} s",
        ),
        Transition(
            State.AVOID,
            State.FORMATION_REVERSE,
            lambda c: c.follower and c.reversing,
            "the group reverses",
            P_DIRECTION,
        ),
        Transition(
            State.AVOID,
            State.FORMATION_TRACK,
            lambda c: c.follower and c.way_free_s >= c.confirm_s,
            "way back to the slot is free",
            P_RESUME,
        ),
    ]


def _should_avoid(c: StackContext) -> bool:
    # A blocked leader means the whole group is about to change course (handover,
    # deadlock): a follower keeps with the group rather than leave it.
    return (
        c.reactive
        and c.follower
        and c.blocked_s >= c.confirm_s
        and not c.reversing
        and not c.leader_blocked
        and c.leader_state not in DEADLOCK_STATES
    )


def _scripted(c: StackContext) -> bool:
    return c.plan == "scripted"


def _backed_off(c: StackContext) -> bool:
    return c.reversed_m >= c.safe_distance_m or c.path_used_up


def _behind(c: StackContext) -> bool:
    return c.imminent or c.someone_stopped


def _navigation_transitions() -> list[Transition[StackContext]]:
    plans = (State.NAVIGATE, State.WANDER, State.EMERGENCY_STOP)
    give_up: list[Transition[StackContext]] = [
        Transition(
            s,
            State.STUCK,
            lambda c: c.is_leader and c.deadlock and not c.retries_left,
            "deadlock and no retries left",
            P_GIVE_UP,
            detail=lambda c: c.stuck_reason,
        )
        for s in plans
    ]
    reverse: list[Transition[StackContext]] = [
        Transition(
            s,
            State.DEADLOCK_REVERSE,
            lambda c: c.is_leader and c.deadlock and c.retries_left,
            "deadlock",
            P_DEADLOCK,
            detail=lambda c: c.deadlock_reason,
        )
        for s in plans
    ]
    return [
        *give_up,
        *reverse,
        Transition(
            State.NAVIGATE,
            State.ARRIVED,
            lambda c: c.is_leader and c.arrived,
            "last waypoint reached",
            P_ARRIVE,
        ),
        Transition(
            State.DEADLOCK_REVERSE,
            State.NAVIGATE,
            lambda c: _scripted(c) and (_backed_off(c) or _behind(c)),
            "backed off: the script resumes",
            P_BEHIND,
            detail=lambda c: f"{c.reversed_m:.2f} m of {c.safe_distance_m:.2f} m",
        ),
        Transition(
            State.DEADLOCK_REVERSE,
            State.DEADLOCK_TURN,
            lambda c: not _scripted(c) and _behind(c),
            "obstacle behind: stop reversing",
            P_BEHIND,
            detail=lambda c: f"after {c.reversed_m:.2f} m",
        ),
        Transition(
            State.DEADLOCK_REVERSE,
            State.DEADLOCK_TURN,
            lambda c: not _scripted(c) and _backed_off(c),
            "backed off the safe distance",
            P_RESUME,
            detail=lambda c: f"{c.reversed_m:.2f} m",
        ),
        *_leader_targets((State.DEADLOCK_TURN,), lambda c: c.turned, "turned away", P_RESUME),
        *_leader_targets(
            (State.DEADLOCK_TURN,),
            lambda c: c.someone_stopped,
            "a robot stopped for an obstacle: the turn ends here",
            P_BEHIND,
        ),
    ]


def behaviour_transitions() -> list[Transition[StackContext]]:
    """Every transition of the behaviour stack (navigation and formation layers)."""
    return [
        *_safety_transitions(),
        *_role_transitions(),
        *_formation_transitions(),
        *_navigation_transitions(),
    ]


def behaviour_machine(initial: str = State.HOLD) -> StateMachine[StackContext]:
    """A fresh behaviour state machine starting in `initial`."""
    return StateMachine(
        initial=initial,
        transitions=behaviour_transitions(),
        absorbing=frozenset({State.STUCK}),
    )


STATE_NOTES: dict[str, str] = {
    State.NAVIGATE: "leader: script, or go to the next waypoint steering round obstacles",
    State.WANDER: "leader without waypoints: cruise, new heading now and then",
    State.ARRIVED: "leader at the last waypoint: stopped",
    State.DEADLOCK_REVERSE: "leader: back off in formation (followers FORMATION_REVERSE)",
    State.DEADLOCK_TURN: "leader: turn in place towards the open side",
    State.AVOID: "follower off its slot, going round an obstacle",
    State.EMERGENCY_STOP: "brake to a standstill",
    State.STUCK: "stopped for good; the reason is in the transition log",
    State.FORMATION_TRACK: "follower tracks its slot forwards",
    State.FORMATION_REVERSE: "follower tracks its slot backwards",
    State.HOLD: "follower stopped: nobody to track",
    State.JOIN: "restarted: stopped until it hears the fleet's leader and epoch",
}
