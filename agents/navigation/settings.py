"""What navigation reads of a scenario, taken from it once where the brain is wired
(`phalanx.agents.parts`): the behaviours and the sense stage are given this, not the
whole scenario.
"""

from __future__ import annotations

from dataclasses import dataclass

from phalanx.agents.navigation.plan import Plan
from phalanx.core.config import DeadlockConfig, NavigationConfig


@dataclass(frozen=True, slots=True)
class NavSettings:
    """The scenario's `[navigation]` and `[deadlock]` tables, what its leader does
    (`plan`), and the control step (s).
    """

    nav: NavigationConfig
    deadlock: DeadlockConfig
    plan: Plan
    dt_s: float
