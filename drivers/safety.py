"""Safety every backend gets, in one place: limits, a command watchdog, E-stop, clean close.

`SafeDriver` wraps any `Driver`:
- every command is clamped to the robot's limits, the tighter of the configured ones and
  those the robot reports (`robot_limits()`, e.g. the ARCOS CONFIG packet), scaling v and
  omega together so the path's curvature is kept; a non-finite command stops the robot;
- a watchdog thread stops the robot when no command has come for `watchdog_s` (0.5 s by
  default: well inside ARCOS's own 2 s and RosAria's 0.6 s);
- `estop()` latches: commands are refused until `reset_estop()`;
- `close()` stops the motors and closes the backend; it is safe to call twice, and the
  context manager calls it on the way out whatever happened.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, replace

from phalanx.core.errors import DriverError
from phalanx.core.geometry import Twist2D
from phalanx.core.lifecycle import Closing
from phalanx.core.limits import SafetyLimits
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.drivers.base import Driver

log = logging.getLogger("phalanx.safety")


@dataclass
class SafetyStats:
    """What the wrapper did."""

    commands: int = 0
    clamped: int = 0
    rejected: int = 0
    watchdog_stops: int = 0
    driver_errors: int = 0


def clamp_twist(twist: Twist2D, v_max_mps: float, omega_max_radps: float) -> Twist2D:
    """`twist` scaled down (curvature kept) to fit both bounds; zero if non-finite."""
    v, w = twist.v_mps, twist.omega_radps
    if not (math.isfinite(v) and math.isfinite(w)):
        return Twist2D(0.0, 0.0)
    scale = 1.0
    if abs(v) > v_max_mps:
        scale = min(scale, v_max_mps / abs(v))
    if abs(w) > omega_max_radps:
        scale = min(scale, omega_max_radps / abs(w))
    return Twist2D(v * scale, w * scale)


class SafeDriver(Closing):
    """A Driver with limits, a watchdog and a latched E-stop around another Driver."""

    def __init__(self, driver: Driver, limits: SafetyLimits) -> None:
        self.driver = driver
        self.name = driver.name
        self.configured = limits
        self.limits = limits
        self.stats = SafetyStats()
        self._lock = threading.Lock()
        self._last_command_s = time.monotonic()
        self._moving = False
        self._estopped = False
        self._closed = False
        self._stop = threading.Event()
        self._watchdog: threading.Thread | None = None

    def connect(self) -> None:
        """Connect the backend, adopt its reported limits if tighter, start the watchdog."""
        self.driver.connect()
        reported = getattr(self.driver, "robot_limits", lambda: None)()
        if reported is not None:
            v_max, w_max = reported
            self.limits = SafetyLimits(
                min(self.configured.v_max_mps, v_max),
                min(self.configured.omega_max_radps, w_max),
                self.configured.watchdog_s,
            )
        self._last_command_s = time.monotonic()
        if self._watchdog is None:
            self._stop.clear()
            self._watchdog = threading.Thread(target=self._watch, name="watchdog", daemon=True)
            self._watchdog.start()

    def set_velocity(self, twist: Twist2D) -> Twist2D:
        """Send `twist` within the limits; returns what was sent (zero when refused)."""
        with self._lock:
            if self._closed:
                raise DriverError("driver closed")
            self.stats.commands += 1
            self._last_command_s = time.monotonic()
            if self._estopped:
                self.stats.rejected += 1
                return Twist2D(0.0, 0.0)
            safe = clamp_twist(twist, self.limits.v_max_mps, self.limits.omega_max_radps)
            if not (math.isfinite(twist.v_mps) and math.isfinite(twist.omega_radps)):
                self.stats.rejected += 1
                log.error("non-finite command %s refused; stopping", twist)
            elif safe != twist:
                self.stats.clamped += 1
            self.driver.set_velocity(safe)
            self._moving = safe.v_mps != 0.0 or safe.omega_radps != 0.0
            return safe

    def read_odometry(self) -> Odometry:
        """The backend's odometry."""
        return self.driver.read_odometry()

    def read_status(self) -> RobotStatus:
        """The backend's status, with the latched E-stop folded in."""
        status = self.driver.read_status()
        if self._estopped and not status.estopped:
            return replace(status, motors_enabled=False, estopped=True)
        return status

    def stop(self) -> None:
        """Bring the robot to rest."""
        with self._lock:
            self._stop_locked()

    def estop(self) -> None:
        """Emergency stop, latched until `reset_estop()`."""
        with self._lock:
            self._estopped = True
            self._moving = False
            self.driver.estop()

    def reset_estop(self) -> None:
        """Accept commands again after an E-stop (re-enables the motors by reconnecting)."""
        with self._lock:
            self._estopped = False
        self.driver.connect()

    def close(self) -> None:
        """Stop and close the backend; safe to call twice."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._stop.set()
            try:
                self._stop_locked()
            finally:
                self.driver.close()
        if self._watchdog is not None:
            self._watchdog.join(2.0)
            self._watchdog = None

    def __enter__(self) -> SafeDriver:
        self.connect()
        return self

    def _stop_locked(self) -> None:
        self._moving = False
        try:
            self.driver.stop()
        except DriverError as exc:
            self.stats.driver_errors += 1
            log.warning("stop failed: %s", exc)

    def _watch(self) -> None:
        period_s = min(0.05, self.limits.watchdog_s / 4)
        while not self._stop.wait(period_s):
            with self._lock:
                late = time.monotonic() - self._last_command_s > self.limits.watchdog_s
                if late and self._moving and not self._closed:
                    self.stats.watchdog_stops += 1
                    log.warning("no command for %.2f s: stopping", self.limits.watchdog_s)
                    self._stop_locked()
