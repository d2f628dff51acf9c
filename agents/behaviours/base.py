"""What every behaviour is: an object with its own state that turns one step's inputs
into a twist (before the limiter), told when it becomes active and, while active, what
the robot's motion did since the last step.

A behaviour reads a `Moment`, built once per step and never written; what it needs to
remember is its own (or one of the shared memories of `phalanx.agents.memory` or of
navigation's, `Steering` and `Course`, it was given when it was made, with the settings
it reads). What the state machine's guards need of it they ask through
the agent when the next step's context is built, never by a command writing to it; what
another behaviour needs of it (the forward twist it drove, `drove_forward`, which a
deadlock reverse retraces) it reports, and the agent hands on in the next `Moment`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from phalanx.agents.inputs import FleetView
from phalanx.agents.sensing import STANDSTILL_MPS, Sensing
from phalanx.core.frozen import quick_init
from phalanx.core.geometry import ZERO_TWIST, Pose2D, Twist2D
from phalanx.core.robot import Odometry


@quick_init
@dataclass(frozen=True, slots=True)
class Moment:
    """One step as a behaviour sees it: fleet time (s), the behaviour state the machine
    is in, the robot's odometry and sensing, its view of the fleet, whether robots of
    the group are off their slots or holding still (`others_busy`), the last forward
    twist a behaviour drove (`last_forward`, reported by it as `drove_forward`), and the
    twist an operator drives the robot with (`operator`: None while none does).
    """

    t_s: float
    state: str
    odometry: Odometry
    sensing: Sensing
    view: FleetView
    others_busy: bool = False
    last_forward: Twist2D = ZERO_TWIST
    operator: Twist2D | None = None

    @property
    def pose(self) -> Pose2D:
        """The robot's pose (odometry, world frame)."""
        return self.odometry.pose


class Behaviour:
    """Base of the behaviours: stand still, remember nothing (subclasses override).

    `emergency`: its stop cannot wait, so the limiter brakes it at the robot's emergency
    limits rather than the comfortable ones.
    """

    emergency = False
    # The forward twist its last command drove (before limits; None: none this step),
    # for a deadlock reverse to retrace.
    drove_forward: Twist2D | None = None

    def enter(self, moment: Moment) -> None:
        """The machine has just entered this behaviour's state (entry action)."""

    def leave(self, moment: Moment) -> None:
        """The machine has just left this behaviour's state (exit action)."""

    def observe(self, odometry: Odometry, previous: Odometry) -> None:
        """While active: the robot moved from `previous` to `odometry` since last step."""

    def command(self, moment: Moment) -> Twist2D:
        """The twist wanted this step (before the limiter)."""
        return ZERO_TWIST


class StandStill(Behaviour):
    """Brake to a standstill and stay there (the limiter ramps the stop): HOLD, JOIN,
    ARRIVED, EMERGENCY_STOP, STUCK and the robot's own stops (E-stop, fault, battery).
    With `emergency` (HOLD: the robot it tracks is gone, so where it is going is unknown)
    at the robot's emergency deceleration.
    """

    def __init__(self, *, emergency: bool = False) -> None:
        self.emergency = emergency


class EmergencyStop(StandStill):
    """EMERGENCY_STOP: brake to a standstill, remembering which way the robot was moving
    when it stopped (`way`, +1 forwards, -1 backwards), which is the side its obstacle
    is on. The robot publishes it as its `direction` while it stands, so a leader about
    to reverse the group can tell a robot stopped for what lies behind (in the way of
    the reverse) from one stopped for what lay ahead.
    """

    def __init__(self) -> None:
        super().__init__()
        self.way = 1

    def enter(self, moment: Moment) -> None:
        """Remember the way the robot was moving (forwards if it was not moving)."""
        self.way = -1 if moment.odometry.twist.v_mps < -STANDSTILL_MPS else 1


def turn_on_spot(error_rad: float, gain_per_s: float, cap_radps: float) -> Twist2D:
    """Turn on the spot towards a heading `error_rad` away (wrapped to [-pi, pi) by the
    caller): proportional, `gain_per_s` x |error|, at most `cap_radps`.
    """
    rate = min(cap_radps, gain_per_s * abs(error_rad))
    return Twist2D(0.0, math.copysign(rate, error_rad))
