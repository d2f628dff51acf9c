"""The `sim` backend on its own: one simulated P3DX body stepped in real time in this process.

Inside a fleet run the `sim` robots are driven by the world process (sense frames and
commands over Zenoh, see `phalanx.agents.runtime`); this class is the same robot model
behind the plain Driver protocol, for the conformance suite, demos and tools that want a
robot without a world.
"""

from __future__ import annotations

import threading
import time

from phalanx.core.errors import DriverError
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.motion import Body
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.core.robot_params import RobotParams


class SimDriver:
    """A simulated P3DX stepped at `rate_hz` by a background thread."""

    name = "sim"

    def __init__(self, robot: RobotParams, *, rate_hz: float = 100.0) -> None:
        self.robot = robot
        self.body = Body(robot)
        self.rate_hz = rate_hz
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._enabled = False
        self._estopped = False
        self._closed = False
        self._odometry = Odometry(Pose2D(0.0, 0.0, 0.0), Twist2D(0.0, 0.0), time.monotonic())

    def connect(self) -> None:
        """Enable the motors and start stepping."""
        with self._lock:
            if self._closed:
                raise DriverError("driver closed; make a new one")
            self._enabled, self._estopped = True, False
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="sim-driver", daemon=True)
            self._thread.start()

    def set_velocity(self, twist: Twist2D) -> None:
        """New setpoint (ignored while disabled)."""
        with self._lock:
            if self._closed:
                raise DriverError("driver closed")
            if self._enabled:
                self.body.command(twist)

    def read_odometry(self) -> Odometry:
        """Pose and twist of the body."""
        with self._lock:
            return self._odometry

    def read_status(self) -> RobotStatus:
        """Free-space sonar, no bumper hit, full battery."""
        state = self.body.state()
        with self._lock:
            return RobotStatus(
                sonar_ranges_m=self.body.sonar_ranges_m(),
                bumpers=(False,) * 14,
                battery_v=12.5,
                motors_enabled=self._enabled,
                estopped=self._estopped,
                stalled=state.stalled,
            )

    def stop(self) -> None:
        """Setpoint zero."""
        self.body.command(Twist2D(0.0, 0.0))

    def estop(self) -> None:
        """Setpoint zero and motors disabled until `connect()`."""
        with self._lock:
            self._enabled, self._estopped = False, True
            self.body.command(Twist2D(0.0, 0.0))

    def close(self) -> None:
        """Stop and end the stepping thread; safe twice."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._enabled = False
            self.body.command(Twist2D(0.0, 0.0))
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None

    def _run(self) -> None:
        period_s = 1.0 / self.rate_hz
        last = time.monotonic()
        while not self._stop.wait(period_s):
            now = time.monotonic()
            state = self.body.step(now - last)
            last = now
            with self._lock:
                self._odometry = Odometry(state.pose, state.twist, now)
