"""The Driver protocol every backend implements, and the readings it returns.

A backend talks to one robot (simulated, ARCOS over serial/TCP, or CiA 402 drives over
CAN). Shared safety (clamping, the command watchdog, stop on close) lives in
`phalanx.drivers.safety.SafeDriver`, never in a backend.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from phalanx.core.geometry import Twist2D
from phalanx.core.robot import Odometry, RobotStatus


@runtime_checkable
class Driver(Protocol):
    """One robot's motors and sensors. Units: m, rad, s.

    `set_velocity` only sets a target; the robot keeps it until the next call, `stop`, or
    its own watchdog. `close` stops the motors and is safe to call twice.
    """

    name: str

    def connect(self) -> None:
        """Open the link, run the protocol's handshake, enable the motors."""
        ...

    def set_velocity(self, twist: Twist2D) -> None:
        """Command forward speed (m/s) and yaw rate (rad/s)."""
        ...

    def read_odometry(self) -> Odometry:
        """The latest odometry."""
        ...

    def read_status(self) -> RobotStatus:
        """The latest sonar, bumpers, battery and motor state."""
        ...

    def stop(self) -> None:
        """Bring the robot to rest now (motors stay enabled)."""
        ...

    def estop(self) -> None:
        """Emergency stop: motors stopped and disabled until reconnect."""
        ...

    def close(self) -> None:
        """Stop the motors and release the link; safe to call twice."""
        ...
