"""What every follower controller reads, and the exact rigid-body target they aim at.

Slot convention (docs/ARCHITECTURE.md, conventions): the follower's slot is
`s = (l cos phi, l sin phi)` in the leader's body frame, phi counter-clockwise from the
leader's heading.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from phalanx.core.frozen import quick_init
from phalanx.core.geometry import Pose2D, Twist2D, Vec2


@quick_init
@dataclass(frozen=True, slots=True)
class FollowerInput:
    """One control step's inputs for a follower (SI units, world frame): the leader's
    pose as it was `leader_age_s` ago, and (`leader_now`) that pose dead-reckoned to
    now, when the caller has worked it out already (the agent does, once per step);
    likewise `target`, the slot's rigid-body target pose and feed-forward twist laid
    out from `leader_now` (`rigid_body_target`).
    """

    follower: Pose2D
    follower_twist: Twist2D
    leader: Pose2D
    leader_twist: Twist2D
    leader_age_s: float
    slot: Vec2
    direction: int
    dt_s: float
    leader_now: Pose2D | None = None
    target: tuple[Pose2D, Twist2D] | None = None


class FollowerController(Protocol):
    """A follower control law: inputs in, unsaturated twist out."""

    def command(self, inp: FollowerInput) -> Twist2D:
        """The twist the follower should drive now (before limits)."""
        ...

    def reset(self) -> None:
        """Forget any internal state."""
        ...
