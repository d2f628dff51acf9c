"""What a robot reports, whatever drives it: odometry and the rest of its status. The
simulated world, every driver backend and the agent's observation use these types.
"""

from __future__ import annotations

from dataclasses import dataclass

from phalanx.core.frozen import quick_init
from phalanx.core.geometry import Pose2D, Twist2D


@quick_init
@dataclass(frozen=True, slots=True)
class Odometry:
    """Dead-reckoned pose (odometry frame) and measured twist, at `stamp_s` (monotonic)."""

    pose: Pose2D
    twist: Twist2D
    stamp_s: float


@dataclass(frozen=True, slots=True)
class TruePose:
    """Where a simulator says the robot really is: `odometry` (its world frame, with the
    twist and the time of the reading), which simulator (`source`), and how fast its clock
    runs (`clock_rate`: simulated seconds a real second, 1 when it keeps real time; AMRISim
    loses a few ms each 100 ms update on a busy machine).
    """

    odometry: Odometry
    source: str
    clock_rate: float = 1.0


@quick_init
@dataclass(frozen=True, slots=True)
class RobotStatus:
    """Everything a driver reads from a robot besides odometry.

    `truth`: where a simulator says the robot really is, for the run's record only: a
    simulated robot's driver can report it (AMRISim's SIMSTAT), a real robot's cannot,
    and no agent steers by it.
    """

    sonar_ranges_m: tuple[float, ...] = ()
    bumpers: tuple[bool, ...] = ()
    battery_v: float | None = None
    motors_enabled: bool = False
    estopped: bool = False
    stalled: bool = False
    faults: tuple[str, ...] = ()
    truth: TruePose | None = None
