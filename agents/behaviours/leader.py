"""The formation leader's behaviours: the scripted motion profile (the paper's piecewise
constant velocities) and the deadlock reverse (section 3.2: when every robot is blocked,
the whole group backs off to a safe distance without turning the formation around).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from phalanx.agents.fsm import State, StateMachine, Transition, TransitionEvent
from phalanx.config import DeadlockConfig, LeaderProfile
from phalanx.geometry import ZERO_TWIST, Twist2D


class ScriptedProfile:
    """Piecewise constant twist over profile time (s); zero after the end unless repeating."""

    def __init__(self, profile: LeaderProfile) -> None:
        self._segments = profile.segments
        self._repeat = profile.repeat
        self._total_s = sum(s.duration_s for s in profile.segments)

    def twist_at(self, profile_time_s: float) -> Twist2D:
        """The scripted twist at `profile_time_s` seconds into the profile."""
        t = profile_time_s % self._total_s if self._repeat else profile_time_s
        for segment in self._segments:
            if t < segment.duration_s:
                return Twist2D(segment.v_mps, math.radians(segment.omega_degps))
            t -= segment.duration_s
        return ZERO_TWIST


@dataclass
class LeaderContext:
    """What the leader's guards read, refreshed every step."""

    blocked: tuple[str, ...] = ()
    everyone_blocked: bool = False
    reversed_m: float = 0.0


class LeaderBehaviour:
    """NAVIGATE (scripted profile) <-> DEADLOCK_REVERSE, with its transition log."""

    def __init__(self, profile: LeaderProfile, deadlock: DeadlockConfig) -> None:
        self.profile = ScriptedProfile(profile)
        self.deadlock = deadlock
        self.profile_time_s = 0.0
        self._last_forward = ZERO_TWIST
        self.context = LeaderContext()
        self.fsm: StateMachine[LeaderContext] = StateMachine(
            initial=State.NAVIGATE,
            transitions=self._transitions(),
            on_entry={State.DEADLOCK_REVERSE: self._start_reverse},
        )

    def _transitions(self) -> list[Transition[LeaderContext]]:
        safe_m = self.deadlock.safe_distance_m
        return [
            Transition(
                State.NAVIGATE,
                State.DEADLOCK_REVERSE,
                lambda c: c.everyone_blocked,
                "every robot reports an obstacle",
                priority=10,
            ),
            Transition(
                State.DEADLOCK_REVERSE,
                State.NAVIGATE,
                lambda c: c.reversed_m >= safe_m,
                f"backed off the safe distance {safe_m:.2f} m",
            ),
        ]

    def _start_reverse(self, ctx: LeaderContext) -> None:
        ctx.reversed_m = 0.0

    @property
    def direction(self) -> int:
        """+1 while moving forwards, -1 during the deadlock reverse."""
        return -1 if self.fsm.state == State.DEADLOCK_REVERSE else 1

    def observe(
        self, *, blocked: tuple[str, ...], everyone_blocked: bool, odometry_step_m: float
    ) -> None:
        """Refresh the guards' context from this step's sensing."""
        self.context.blocked = blocked
        self.context.everyone_blocked = everyone_blocked
        if self.fsm.state == State.DEADLOCK_REVERSE:
            self.context.reversed_m += odometry_step_m

    def update(self, t_s: float) -> TransitionEvent | None:
        """Take a transition if a guard holds."""
        return self.fsm.update(self.context, t_s)

    def wanted_twist(self, dt_s: float) -> Twist2D:
        """The leader's unsaturated command for this step; advances the profile clock.

        The profile clock pauses while reversing, so the script resumes where it left off.
        """
        if self.fsm.state == State.DEADLOCK_REVERSE:
            return self._reverse_twist()
        twist = self.profile.twist_at(self.profile_time_s)
        self.profile_time_s += dt_s
        self._last_forward = twist
        return twist

    def _reverse_twist(self) -> Twist2D:
        speed = self.deadlock.reverse_speed_mps
        if self.deadlock.reverse_mode == "fixed" or abs(self._last_forward.v_mps) < 1e-6:
            return Twist2D(-speed, math.radians(self.deadlock.reverse_omega_degps))
        curvature_per_m = self._last_forward.omega_radps / self._last_forward.v_mps
        return Twist2D(-speed, -speed * curvature_per_m)
