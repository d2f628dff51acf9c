"""One simulated P3DX body on its own: unicycle kinematics under the robot's velocity and
acceleration limits, a stall switch, and sonar ranges from an optional obstacle set.

Thread-safe. The ARCOS robot emulator and the in-process `sim` driver both move one of
these; the world simulator (`phalanx.simulator.world`) is the multi-robot counterpart.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

from phalanx.core.geometry import Pose2D, Twist2D, integrate_unicycle
from phalanx.core.robot_params import RobotParams


def _towards(current: float, target: float, max_step: float) -> float:
    return current + max(-max_step, min(max_step, target - current))


@dataclass
class BodyState:
    """A snapshot of the body."""

    pose: Pose2D
    twist: Twist2D
    setpoint: Twist2D
    stalled: bool
    odometer_m: float


class Body:
    """A P3DX that follows velocity setpoints within its limits."""

    def __init__(self, robot: RobotParams, start: Pose2D | None = None) -> None:
        self.robot = robot
        self._lock = threading.Lock()
        self._pose = start or Pose2D(0.0, 0.0, 0.0)
        self._twist = Twist2D(0.0, 0.0)
        self._setpoint = Twist2D(0.0, 0.0)
        self._stalled = False
        self._odometer_m = 0.0

    def command(self, setpoint: Twist2D) -> None:
        """New velocity setpoint (clamped to the robot's rated limits)."""
        v_max, w_max = self.robot.v_max_mps, math.radians(self.robot.omega_max_degps)
        with self._lock:
            self._setpoint = Twist2D(
                max(-v_max, min(v_max, setpoint.v_mps)),
                max(-w_max, min(w_max, setpoint.omega_radps)),
            )

    def stall(self, stalled: bool) -> None:
        """Block (or free) the wheels: a stalled body does not move."""
        with self._lock:
            self._stalled = stalled

    def step(self, dt_s: float) -> BodyState:
        """Advance `dt_s`: velocities approach the setpoint at the acceleration limits."""
        r = self.robot
        with self._lock:
            target = Twist2D(0.0, 0.0) if self._stalled else self._setpoint
            accel = r.accel_mps2 if abs(target.v_mps) > abs(self._twist.v_mps) else r.decel_mps2
            v = _towards(self._twist.v_mps, target.v_mps, accel * dt_s)
            w = _towards(
                self._twist.omega_radps, target.omega_radps, math.radians(r.rot_accel_degps2) * dt_s
            )
            self._twist = Twist2D(v, w)
            self._pose = integrate_unicycle(self._pose, self._twist, dt_s)
            self._odometer_m += abs(v) * dt_s
            return self._snapshot()

    def state(self) -> BodyState:
        """The current snapshot."""
        with self._lock:
            return self._snapshot()

    def state_at(self, t_s: float) -> BodyState:
        """The snapshot at monotonic time `t_s`: this body is where its owner last
        stepped it, which an emulator sending a SIP of the cycle at `t_s` has done.
        """
        del t_s
        return self.state()

    def _snapshot(self) -> BodyState:
        return BodyState(self._pose, self._twist, self._setpoint, self._stalled, self._odometer_m)

    def sonar_ranges_m(self) -> tuple[float, ...]:
        """Free space all round: every sonar at its maximum range."""
        return (self.robot.sonar.max_range_m,) * len(self.robot.sonar.units)
