"""The agent process on a robot driver (`phalanx agent --driver arcos|canopen`).

The robot, not a world process, supplies odometry and sensors, so the agent keeps its
own clock: control steps at `epoch + k * dt` on the wall clock (Unix time; every agent
and the world of a fleet are given the same epoch, so their scenario times agree within
the hosts' clock sync). Each step reads the driver, turns its odometry (which starts at
zero where the robot was switched on) into the shared world frame with the robot's start
pose from the scenario, runs the same agent core as the simulated robots, publishes the
state, and sends the command through the safety wrapper. The command is not published
as a `cmd` for a world to execute: the robot executes it.
"""

from __future__ import annotations

import logging
import math
import time

from phalanx.agents.agent import StepOutput
from phalanx.core.config import RobotParams, Scenario
from phalanx.core.errors import DriverError
from phalanx.core.geometry import Pose2D, dead_reckon
from phalanx.core.robot import Odometry, start_pose
from phalanx.drivers.safety import SafeDriver
from phalanx.runtime.agent import AgentRuntime, RuntimeOptions
from phalanx.runtime.signals import Stoppable
from phalanx.telemetry.stream import Telemetry
from phalanx.wire.messages import SenseFrame

log = logging.getLogger("phalanx.agent")
# Odometry is dead-reckoned to the control instant over at most this long: an ARCOS SIP is
# up to 100 ms old when a step reads it, a CiA 402 TPDO up to 20 ms. Older readings (a
# link about to be declared lost) are carried forward by this much only.
MAX_ODOMETRY_AGE_S = 0.25


def pose_now(odometry: Odometry, now_s: float) -> Pose2D:
    """The odometry pose carried forward along its twist from its stamp to `now_s`.

    Without this a follower steers from where it was at the last SIP, not where it is:
    a lag that depends on the phase between its SIP cycle and its control clock, and
    shows as a steady slot error of several millimetres at the paper's speeds.
    """
    age_s = now_s - odometry.stamp_s
    return dead_reckon(odometry.pose, odometry.twist, age_s, MAX_ODOMETRY_AGE_S)


class DriverRuntime(AgentRuntime):
    """An AgentRuntime whose ticks come from its own clock and whose robot is a driver."""

    publish_commands = False

    def __init__(
        self,
        robot_id: str,
        scenario: Scenario,
        robot: RobotParams,
        options: RuntimeOptions,
        driver: SafeDriver,
        *,
        epoch_s: float,
        telemetry: Telemetry | None = None,
    ) -> None:
        super().__init__(robot_id, scenario, robot, options, telemetry=telemetry)
        self.driver = driver
        self.epoch_s = epoch_s
        self.origin = start_pose(scenario, robot_id)
        self.driver_errors = 0
        self.overruns = 0

    def _loop(self, stop: Stoppable) -> None:
        dt_s = self.scenario.dt_s
        steps = round(self.scenario.duration_s / dt_s)
        if self.epoch_s > time.time() and stop.wait(self.epoch_s - time.time()):
            return
        k = max(0, math.ceil((time.time() - self.epoch_s) / dt_s))
        try:
            while k < steps and not stop.is_set():
                wait_s = self.epoch_s + k * dt_s - time.time()
                if wait_s > 0 and stop.wait(wait_s):
                    break
                late_ticks = math.floor((time.time() - self.epoch_s) / dt_s) - k
                if late_ticks > 0:  # skip what cannot be done in time rather than bunch up
                    self.overruns += 1
                    k += late_ticks
                self._drive(k)
                k += 1
        finally:
            self.driver.stop()

    def _drive(self, k: int) -> StepOutput | None:
        try:
            odometry = self.driver.read_odometry()
            status = self.driver.read_status()
        except DriverError as exc:
            self.driver_errors += 1
            log.warning("%s: no reading from the robot at step %d: %s", self.robot_id, k, exc)
            return None
        pose = self.origin.compose(pose_now(odometry, time.monotonic()))
        # A backend without sonar (CAN drives) reports free space: it never blocks.
        sonar = status.sonar_ranges_m or (self.robot.sonar.max_range_m,) * len(
            self.robot.sonar.units
        )
        frame = SenseFrame(
            robot_id=self.robot_id,
            tick=k,
            t_s=k * self.scenario.dt_s,
            dt_s=self.scenario.dt_s,
            x_m=pose.x_m,
            y_m=pose.y_m,
            theta_rad=pose.theta_rad,
            v_mps=odometry.twist.v_mps,
            omega_radps=odometry.twist.omega_radps,
            sonar_ranges_m=sonar,
            bumpers=status.bumpers,
        )
        out = self.step(frame)
        try:
            self.driver.set_velocity(out.command)
        except DriverError as exc:
            self.driver_errors += 1
            log.warning("%s: command not sent at step %d: %s", self.robot_id, k, exc)
        return out
