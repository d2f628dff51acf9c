"""Every transition of the behaviour stack, layer by layer (the robot's own stops, the
emergency stop and leadership, the formation layer, the navigation layer, an operator
driving the leader), with the priorities that arbitrate between them: a higher priority
wins whenever its guard holds. The order of the transitions within one priority is the
order they are tried in.
"""

from __future__ import annotations

from phalanx.agents.behaviours.context import Guard, StackContext
from phalanx.agents.fsm import ANY_STATE, Transition
from phalanx.agents.navigation import Plan
from phalanx.core.states import DEADLOCK_STATES, LEADER_STATES, ROBOT_STATES, State

# Priorities of the transitions below; a row wins over every row beneath it.
P_STUCK = 100
P_ROBOT = 99
P_BEHIND = 95
P_ESTOP = 90
P_ROLE = 80
P_HOLD = 70
P_TELEOP = 68
P_GIVE_UP = 65
P_DEADLOCK = 60
P_RESHAPE = 50
P_AVOID = 40
P_DIRECTION = 30
P_ARRIVE = 20
P_RESUME = 10


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
    arrive: bool = True,
) -> list[Transition[StackContext]]:
    """`sources` -> the leader state the plan calls for, when `guard` also holds
    (`arrive`: ARRIVED is one of them; not where a transition of its own leads there).
    """
    targets: list[tuple[str, Guard]] = [
        (State.WANDER, _leads("wander", arrived=False)),
        (State.NAVIGATE, _leads("goto", arrived=False)),
    ]
    if arrive:
        targets.insert(0, (State.ARRIVED, _leads(None, arrived=True)))
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
            lambda c: c.reactive and (c.bumper or c.imminent) and c.joined and not c.robot_halted,
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
            lambda c: c.standstill and c.way_clear and not c.bumper and not c.operator,
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
        and c.leader_state != State.RESHAPE
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
            State.RESHAPE,
            lambda c: c.is_leader and c.plan == "goto" and c.reshape_wanted and not c.arrived,
            "the way ahead needs another shape: slide every slot to it on the move",
            P_RESHAPE,
        ),
        *_leader_targets(
            (State.RESHAPE,), lambda c: c.reshaped, "reshaped", P_RESUME, arrive=False
        ),
        Transition(
            State.NAVIGATE,
            State.ARRIVED,
            lambda c: c.is_leader and c.arrived,
            "last waypoint reached",
            P_ARRIVE,
        ),
        Transition(
            State.RESHAPE,
            State.ARRIVED,
            lambda c: c.is_leader and c.arrived,
            "last waypoint reached: a slide under way ends standing",
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
        # (A robot stopping for an obstacle does not end the turn: ending it there left a
        # boxed-in group reversing and turning by inches, over and over; docs/RESULTS.md.)
        *_leader_targets((State.DEADLOCK_TURN,), lambda c: c.turned, "turned away", P_RESUME),
    ]


# The leader's own driving an operator may take over: its plan, the deadlock escape, a
# stop at the goal (a slide between shapes under way finishes first).
_OPERATED = (
    State.NAVIGATE, State.WANDER, State.ARRIVED, State.DEADLOCK_REVERSE, State.DEADLOCK_TURN,
)  # fmt: skip


def _operator_transitions() -> list[Transition[StackContext]]:
    """An operator's twist drives the leader (TELEOP) while commands keep coming; from an
    emergency stop only once the robot stands and the way it is asked to go is clear.
    """
    drives = "an operator drives the leader"
    return [
        *(
            Transition(s, State.TELEOP, lambda c: c.is_leader and c.operator, drives, P_TELEOP)
            for s in _OPERATED
        ),
        Transition(
            State.EMERGENCY_STOP,
            State.TELEOP,
            lambda c: (
                c.is_leader and c.operator and c.standstill and c.operator_clear and not c.bumper
            ),
            f"came to a standstill, {drives} a clear way",
            P_TELEOP,
        ),
        *_leader_targets(
            (State.TELEOP,),
            lambda c: not c.operator,
            "the operator's commands stopped: back to the plan",
            P_RESUME,
        ),
        Transition(
            State.ARRIVED,
            State.NAVIGATE,
            lambda c: c.is_leader and c.plan == "goto" and not c.arrived,
            "a new goal",
            P_RESUME,
        ),
    ]


def _battery(c: StackContext) -> str:
    return "" if c.battery_v is None else f"{c.battery_v:.1f} V"


def _robot_transitions() -> list[Transition[StackContext]]:
    """The robot's own conditions, exclusive and in this order: E-stop, fault, stall,
    battery; each holds the robot still until it clears.
    """
    fine = "the robot is fine again"
    return [
        Transition(ANY_STATE, State.ESTOPPED, lambda c: c.estopped,
                   "the robot's emergency stop is engaged", P_ROBOT),
        Transition(ANY_STATE, State.FAULT, lambda c: bool(c.faults) and not c.estopped,
                   "the robot reports a fault", P_ROBOT, detail=lambda c: "; ".join(c.faults)),
        Transition(ANY_STATE, State.STALLED,
                   lambda c: c.stalled and not c.estopped and not c.faults,
                   "a wheel is stalled", P_ROBOT),
        Transition(ANY_STATE, State.LOW_BATTERY,
                   lambda c: c.battery_low and not (c.estopped or c.faults or c.stalled),
                   "the battery is low", P_ROBOT, detail=_battery),
        *(
            Transition(s, State.FORMATION_TRACK, lambda c: not c.robot_halted and c.follower,
                       f"{fine}: back to the formation", P_RESUME)
            for s in sorted(ROBOT_STATES)
        ),
        *_leader_targets(tuple(sorted(ROBOT_STATES)), lambda c: not c.robot_halted,
                         f"{fine}: back to the plan", P_RESUME),
    ]  # fmt: skip


def behaviour_transitions() -> list[Transition[StackContext]]:
    """Every transition of the behaviour stack (robot, navigation and formation layers)."""
    return [
        *_robot_transitions(),
        *_safety_transitions(),
        *_role_transitions(),
        *_formation_transitions(),
        *_navigation_transitions(),
        *_operator_transitions(),
    ]
