"""How an agent reaches its robot: reading what the robot senses and sending it commands.

- `WorldLink`: a simulated robot, moved by the world process. The world's sense frames
  arrive over Zenoh and are also the agent's clock (one frame, one tick); commands go
  back on `.../cmd`, answered for the frame's tick (in lockstep the world waits on them).
- `DriverIO`: a real robot (or an emulated one) through a driver and the safety wrapper.
  Its odometry starts at zero where the robot was switched on: it is turned into the
  shared world frame with the robot's start pose from the scenario, and carried forward
  from when the robot sent it to the control instant. The robot's whole status reaches
  the agent: E-stop, stall, drive faults and battery included.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace
from typing import Protocol

from phalanx.agents.inputs import Observation
from phalanx.core.errors import DriverError
from phalanx.core.geometry import Pose2D, Twist2D, integrate_unicycle
from phalanx.core.robot import Odometry, RobotStatus, TruePose
from phalanx.core.robot_params import RobotParams
from phalanx.drivers.safety import SafeDriver
from phalanx.runtime.clock import Tick
from phalanx.runtime.frames import Ending, FrameBox, FrameGate
from phalanx.runtime.positioning import PositioningInbox, frame_fixes, frame_relative
from phalanx.runtime.signals import Stoppable
from phalanx.wire.bounds import FleetBounds
from phalanx.wire.codec import DecodeStats
from phalanx.wire.keys import robot_key
from phalanx.wire.messages import RobotState, SenseFrame, VelocityCommand
from phalanx.wire.positions import TruthMessage
from phalanx.wire.transport import FleetSession

log = logging.getLogger("phalanx.agent")
# Odometry is dead-reckoned to the control instant over at most this long: an ARCOS SIP is
# up to 100 ms old when a step reads it, a CiA 402 TPDO up to 20 ms. Older readings (a
# link about to be declared lost) are carried forward by this much only.
MAX_ODOMETRY_AGE_S = 0.25
FRAME_POLL_S = 0.1


class RobotIO(Protocol):
    """One robot's readings in, commands out, step by step."""

    def attach(self, session: FleetSession) -> None:
        """Subscribe to what the robot's side sends over the fleet's session, if any."""
        ...

    def read(self, tick: Tick) -> Observation | None:
        """What the robot senses at `tick` (None: no reading this step, counted)."""
        ...

    def write(self, tick: Tick, command: Twist2D) -> None:
        """Send the command of step `tick`."""
        ...

    def halt(self) -> None:
        """The run is over (or broke off): leave the robot at rest."""
        ...

    def counters(self) -> dict[str, int]:
        """What the robot's side counted (for the status queryable)."""
        ...

    def lag_s(self, tick: Tick) -> float:
        """How far (s) the robot's side has moved on past `tick` already."""
        ...

    def relayed(self) -> tuple[RobotState, ...]:
        """Other robots' states that came with the last reading (the world's frames in
        lockstep), each given once.
        """
        ...

    def heard_s(self) -> float | None:
        """When (monotonic) the robot's side last sent over the fleet's session (None:
        it sends nothing that way, or has not yet).
        """
        ...


def pose_at(odometry: Odometry, at_s: float) -> Pose2D:
    """The odometry pose carried along its twist from its stamp to `at_s`, forwards or
    back (a reading newer than the instant), by at most MAX_ODOMETRY_AGE_S.

    Without this a follower steers from where it was at the last SIP, not where it is:
    a lag that depends on the phase between its SIP cycle and its control clock, and
    shows as a steady slot error of several millimetres at the paper's speeds.
    """
    age_s = max(-MAX_ODOMETRY_AGE_S, min(MAX_ODOMETRY_AGE_S, at_s - odometry.stamp_s))
    if age_s == 0.0:
        return odometry.pose
    return integrate_unicycle(odometry.pose, odometry.twist, age_s)


class WorldLink:
    """A simulated robot: sense frames from the world are its readings and its clock
    (which frames count: `phalanx.runtime.frames.FrameGate`).
    """

    def __init__(
        self,
        fleet: str,
        robot_id: str,
        *,
        frame_timeout_s: float,
        robot_ids: tuple[str, ...] = (),
        bounds: FleetBounds | None = None,
    ) -> None:
        self.fleet, self.robot_id = fleet, robot_id
        self.robot_ids = robot_ids  # the scenario's, in order: relative targets by index
        self.frame_timeout_s = frame_timeout_s
        self.bounds = bounds
        self.world_lost = False  # ended because the world's frames stopped coming
        self.stats = DecodeStats()  # the session's, once attached
        self._box = FrameBox(self.stats)
        self.gate = self._gate()
        self._frame: SenseFrame | None = None
        self._relay_from: SenseFrame | None = None  # the frame whose peers are not taken
        self._session: FleetSession | None = None

    def _gate(self) -> FrameGate:
        bounds = self.bounds
        last_tick = bounds.ticks - 1 if bounds is not None else None
        return FrameGate(self.stats, last_tick=last_tick, dt_s=bounds.dt_s if bounds else 0.1)

    @property
    def ending(self) -> Ending | None:
        """How the world ended the run: at its end, or cut short (None: it did not)."""
        return self.gate.ending

    def attach(self, session: FleetSession) -> None:
        """Take the world's frames for this robot (counted in the session's stats)."""
        self._session = session
        self.stats = session.stats
        self._box = FrameBox(self.stats)
        self.gate = self._gate()
        session.subscribe(
            robot_key(self.fleet, self.robot_id, "sense"),
            SenseFrame,
            lambda _k, f: self._box.put(f),
            context=self.bounds,
        )

    def next_tick(self, stop: Stoppable) -> Tick | None:
        """The next frame's tick; None once the world ended the run (its final frame),
        on `stop`, or when no frame has come for `frame_timeout_s` (`world_lost`).
        """
        last_frame = time.monotonic()
        while not stop.is_set():
            frames = self._box.take(FRAME_POLL_S)
            if frames:
                last_frame = time.monotonic()
            frame = self.gate.offer(frames)
            if frame is not None:
                self._frame = self._relay_from = frame
                return Tick(frame.tick, frame.t_s)
            if self.gate.ended():
                return None
            if time.monotonic() - last_frame > self.frame_timeout_s:
                log.warning(
                    "%s: no frame from the world for %.0f s, stopping (a host daemon "
                    "restarts it to rejoin)",
                    self.robot_id,
                    self.frame_timeout_s,
                )
                self.world_lost = True
                return None
        return None

    def read(self, tick: Tick) -> Observation | None:
        """The frame's odometry and sensors (the world's noise, events and all)."""
        frame = self._frame
        if frame is None or frame.tick != tick.k:
            return None
        odometry = Odometry(
            Pose2D(frame.x_m, frame.y_m, frame.theta_rad),
            Twist2D(frame.v_mps, frame.omega_radps),
            frame.t_s,
        )
        status = RobotStatus(
            sonar_ranges_m=frame.sonar_ranges_m, bumpers=frame.bumpers, motors_enabled=True
        )
        fixes, relative = frame_fixes(frame), frame_relative(frame, self.robot_ids)
        return Observation(odometry, status, fixes=fixes, relative=relative)

    def write(self, tick: Tick, command: Twist2D) -> None:
        """The command for the frame's tick, to the world (which waits on it in lockstep)."""
        if self._session is None:
            return
        message = VelocityCommand(
            robot_id=self.robot_id,
            tick=tick.k,
            stamp_s=tick.t_s,
            v_mps=command.v_mps,
            omega_radps=command.omega_radps,
        )
        key = robot_key(self.fleet, self.robot_id, "cmd")
        self._session.publish(key, message, reliable_block=True)

    def halt(self) -> None:
        """Nothing to do: the world stops a robot whose agent is gone."""

    def heard_s(self) -> float | None:
        """When the last frame arrived (None: none yet; the world may still be waiting
        for the fleet to come).
        """
        return self._box.put_s

    def relayed(self) -> tuple[RobotState, ...]:
        """The other robots' states the frame read last carried (once)."""
        frame, self._relay_from = self._relay_from, None
        return frame.peers if frame is not None else ()

    def lag_s(self, tick: Tick) -> float:
        """How many ticks' time the world has sent past `tick` (frames waiting)."""
        newest = self._box.newest_tick()
        dt_s = self.bounds.dt_s if self.bounds is not None else 0.1
        return 0.0 if newest is None else max(0, newest - tick.k) * dt_s

    def counters(self) -> dict[str, int]:
        """Frames acted on, and skipped as stale (the robot was late)."""
        counts = self.gate.counts
        return {"frames": counts.acted, "frames_skipped": counts.skipped}


class DriverIO:
    """A robot on a driver, through the safety wrapper (limits, watchdog, E-stop).

    Odometry is carried to the instant the step stands for (`epoch_s` + its fleet
    time): a step a loaded machine ran late still describes the robot at its tick, as
    the state it publishes says (its peers predict it from that stamp).

    Where the robot is simulated (AMRISim), its driver also reads where the simulator
    says it really is: each new reading goes out on the robot's `truth` key, for the
    run's record (never into the agent's observation).
    """

    def __init__(
        self,
        driver: SafeDriver,
        robot: RobotParams,
        *,
        origin: Pose2D,
        positioning: PositioningInbox | None = None,
        robot_id: str = "",
        fleet: str = "",
        epoch_s: float | None = None,
    ) -> None:
        self.driver, self.robot, self.origin = driver, robot, origin
        self.epoch_s = epoch_s  # Unix time of step 0 (None: a step stands for its reading)
        self.positioning = positioning
        self.robot_id, self.fleet = robot_id, fleet
        self.driver_errors = 0
        self.commands_sent = 0
        self.truths_sent = 0
        self._session: FleetSession | None = None
        self._truth_s = -math.inf  # the newest truth sent (its driver's monotonic stamp)

    def attach(self, session: FleetSession) -> None:
        """The robot is on this computer's port or bus; its positioning fixes, if it
        uses any, come over the fleet's session, and its true pose, if a simulator gives
        one, goes out over it.
        """
        self._session = session
        if self.positioning is not None:
            self.positioning.attach(session)

    def read(self, tick: Tick) -> Observation | None:
        """Odometry in the world frame at the control instant, and the robot's status."""
        try:
            odometry = self.driver.read_odometry()
            status = self.driver.read_status()
        except DriverError as exc:
            self.driver_errors += 1
            log.warning("no reading from the robot at step %d: %s", tick.k, exc)
            return None
        pose = self.origin.compose(pose_at(odometry, self._instant(tick)))
        if status.truth is not None and status.truth.odometry.stamp_s > self._truth_s:
            self._send_truth(status.truth)
        if not status.sonar_ranges_m:
            # A backend without sonar (CAN drives) reports free space: it never blocks.
            free = (self.robot.sonar.max_range_m,) * len(self.robot.sonar.units)
            status = replace(status, sonar_ranges_m=free)
        fixes, relative = self.positioning.drain() if self.positioning else ((), ())
        return Observation(
            Odometry(pose, odometry.twist, tick.t_s), status, fixes=fixes, relative=relative
        )

    def _instant(self, tick: Tick) -> float:
        """The monotonic time step `tick` stands for (now, without an epoch)."""
        now = time.monotonic()
        if self.epoch_s is None:
            return now
        return now - (time.time() - (self.epoch_s + tick.t_s))

    def _send_truth(self, truth: TruePose) -> None:
        """Publish a simulator's true pose, stamped in Unix time (a message that will
        not validate, a pose out of the wire's bounds, is logged and skipped).
        """
        reading = truth.odometry
        self._truth_s = reading.stamp_s
        if self._session is None or not self.robot_id:
            return
        pose, twist = reading.pose, reading.twist
        try:
            message = TruthMessage(
                robot_id=self.robot_id,
                stamp_s=time.time() - (time.monotonic() - reading.stamp_s),
                x_m=pose.x_m, y_m=pose.y_m, theta_rad=pose.theta_rad,
                v_mps=twist.v_mps, omega_radps=twist.omega_radps, source=truth.source[:32],
                clock_rate=truth.clock_rate,
            )  # fmt: skip
            self._session.publish(robot_key(self.fleet, self.robot_id, "truth"), message)
        except Exception as exc:  # the record's loss, never the robot's control
            log.warning("true pose not sent: %s", exc)
            return
        self.truths_sent += 1

    def write(self, tick: Tick, command: Twist2D) -> None:
        """The command, through the safety wrapper."""
        try:
            self.driver.set_velocity(command)
        except DriverError as exc:
            self.driver_errors += 1
            log.warning("command not sent at step %d: %s", tick.k, exc)
            return
        self.commands_sent += 1

    def halt(self) -> None:
        """Stop the robot (the wrapper keeps it stopped on close too), and its camera."""
        self.driver.stop()
        if self.positioning is not None:
            self.positioning.close()

    def lag_s(self, tick: Tick) -> float:
        """None: the robot's own clock skips the ticks it is late for."""
        return 0.0

    def relayed(self) -> tuple[RobotState, ...]:
        """None: a robot on a driver hears its peers over the fleet's session."""
        return ()

    def heard_s(self) -> float | None:
        """None: the robot's side is its driver, not the fleet's session."""
        return None

    def counters(self) -> dict[str, int]:
        """Readings and commands the driver failed, commands it took, true poses sent."""
        return {
            "driver_errors": self.driver_errors,
            "commands_sent": self.commands_sent,
            "truths_sent": self.truths_sent,
        }
