"""What the behaviour stack's guards read: one frozen context, built by the agent once
per step before the state machine updates, never written afterwards.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from phalanx.agents.navigation import Plan
from phalanx.core.frozen import quick_init


@quick_init
@dataclass(frozen=True)
class StackContext:
    """What the guards read: built once per step, before the machine updates, and never
    written afterwards (a command cannot steer the next step's guards).
    """

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
    # the shape (a leader): another one wanted; a reshape done
    reshape_wanted: bool = False
    reshaped: bool = False
    # an operator: a twist young enough to drive by, and room to brake the way it drives
    operator: bool = False
    operator_clear: bool = True
    # tunables the guards need
    confirm_s: float = 0.2
    threshold_mps: float = 0.02
    # the robot itself, from its driver's status
    estopped: bool = False
    faults: tuple[str, ...] = ()
    stalled: bool = False
    battery_low: bool = False
    battery_v: float | None = None
    # not a guard's: what the step's commands read of the group (robots off their slots)
    others_busy: bool = False

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
    def robot_halted(self) -> bool:
        """The robot's own condition stops it (E-stop, fault, stall, low battery)."""
        return self.estopped or bool(self.faults) or self.stalled or self.battery_low

    @property
    def lost(self) -> bool:
        """A follower with nobody to track."""
        return self.leader_lost or not self.parent_fresh


Guard = Callable[[StackContext], bool]
