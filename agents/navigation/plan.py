"""What a leader does (its `Plan`): the scripted profile of the paper's runs (piecewise
constant velocities, `ScriptedProfile`), go to waypoints along the route, or wander
along a seeded heading that changes now and then (`WanderHeading`).
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from phalanx.core.config import LeaderProfile, NavigationConfig, Scenario
from phalanx.core.geometry import ZERO_TWIST, Pose2D, Twist2D, wrap_angle

Plan = Literal["scripted", "goto", "wander"]


def plan_of(scenario: Scenario) -> Plan:
    """What a leader of `scenario` does: its script, go to waypoints, or wander."""
    if scenario.leader_profile is not None:
        return "scripted"
    return "goto" if scenario.navigation.waypoints else "wander"


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


class WanderHeading:
    """A heading that changes every `wander_period_s` by up to `wander_turn_deg`, drawn
    from a seeded generator: the same on every run of a scenario.
    """

    def __init__(self, nav: NavigationConfig, seed: int) -> None:
        self.period_s = nav.wander_period_s
        self.turn_rad = math.radians(nav.wander_turn_deg)
        self._rng = np.random.default_rng(seed)
        self.heading_rad: float | None = None
        self._next_s = 0.0

    def heading(self, pose: Pose2D, t_s: float) -> float:
        """The world-frame heading to wander along at `t_s`."""
        if self.heading_rad is None:
            self.heading_rad = pose.theta_rad
        if t_s >= self._next_s:
            self._next_s = t_s + self.period_s
            turn = float(self._rng.uniform(-self.turn_rad, self.turn_rad))
            self.heading_rad = wrap_angle(self.heading_rad + turn)
        return self.heading_rad
