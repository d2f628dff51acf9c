"""An emulated P3DX whose body lives in the world process: ARCOS on one side, Zenoh on the
other, so a whole scenario runs with every agent on the `arcos` driver.

The world publishes the robot's sense frame every tick; the bridge hands its pose (in
the robot's own odometry frame, which starts at the scenario's start pose), twist and
sonar ranges to the emulator, and answers each frame with the velocity setpoint the
emulated firmware is executing, as the robot's `cmd`. The agent never talks to the world:
it only sees ARCOS.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable

from phalanx.core.geometry import Pose2D, Twist2D, dead_reckon
from phalanx.core.motion import Body, BodyState
from phalanx.core.robot_params import RobotParams
from phalanx.wire.keys import robot_key
from phalanx.wire.messages import SenseFrame, VelocityCommand
from phalanx.wire.transport import FleetSession, TransportConfig, open_session

log = logging.getLogger("phalanx.emulator")
# A world frame is carried forward at most this long (a world that stopped sending frames
# leaves the body where its last one put it, plus this much of its motion).
MAX_FRAME_AGE_S = 0.25


class WorldBody(Body):
    """A Body whose motion comes from the world's sense frames, not from integration.

    Between frames the pose is carried forward along the frame's twist, as a robot's
    firmware integrates its encoders continuously: a SIP reports where the body is when
    the SIP is sent, not where the world's last tick put it (up to a tick earlier, by an
    amount fixed by the phase between the emulator's SIP cycle and the world's clock,
    which the agents would otherwise see as a steady lag of their own robot). Given the
    run's epoch (`epoch_s`, Unix time of step 0), it is carried from the frame's own
    instant, not from when the frame arrived: a frame delayed on a loaded machine would
    otherwise put the body behind where the world's motion-capture fixes have it.
    """

    def __init__(
        self,
        robot: RobotParams,
        origin: Pose2D,
        clock: Callable[[], float] = time.monotonic,
        *,
        epoch_s: float | None = None,
        wall: Callable[[], float] = time.time,
    ) -> None:
        super().__init__(robot)
        self.origin = origin
        self.clock = clock
        self.epoch_s, self.wall = epoch_s, wall  # the run's step 0 (Unix time), if known
        self._sonar: tuple[float, ...] = super().sonar_ranges_m()
        self._frame_s = clock()
        self.frames = 0
        self.final = threading.Event()

    def update(self, frame: SenseFrame) -> Twist2D:
        """Take the world's frame; return the setpoint to execute until the next one."""
        local = self.origin.relative(Pose2D(frame.x_m, frame.y_m, frame.theta_rad))
        with self._lock:
            self._pose = local
            self._twist = Twist2D(frame.v_mps, frame.omega_radps)
            self._frame_s = self.clock() - self._age(frame)
            if frame.sonar_ranges_m:
                self._sonar = frame.sonar_ranges_m
            self.frames += 1
            return Twist2D(0.0, 0.0) if self._stalled else self._setpoint

    def _age(self, frame: SenseFrame) -> float:
        """How long ago the frame's instant was (0 without the run's epoch): a frame on
        the way for a while, or from a world behind its schedule, describes the body as it
        was then.
        """
        if self.epoch_s is None:
            return 0.0
        return min(max(self.wall() - (self.epoch_s + frame.t_s), 0.0), MAX_FRAME_AGE_S)

    def step(self, dt_s: float) -> BodyState:
        """The world integrates: nothing to do here."""
        del dt_s
        return self.state()

    def state(self) -> BodyState:
        """The snapshot, its pose carried forward from the last frame to now."""
        return self.state_at(self.clock())

    def state_at(self, t_s: float) -> BodyState:
        """The snapshot, its pose carried forward from the last frame to `t_s` (this
        body's clock; not back before the frame).
        """
        with self._lock:
            snapshot = self._snapshot()
            age_s = t_s - self._frame_s
        snapshot.pose = dead_reckon(snapshot.pose, snapshot.twist, age_s, MAX_FRAME_AGE_S)
        return snapshot

    def sonar_ranges_m(self) -> tuple[float, ...]:
        """The world's latest sonar ranges for this robot."""
        with self._lock:
            return self._sonar


class WorldBridge:
    """Wires a WorldBody to the world over Zenoh."""

    def __init__(self, body: WorldBody, robot_id: str, fleet: str) -> None:
        self.body = body
        self.robot_id = robot_id
        self.fleet = fleet
        self._session: FleetSession | None = None

    def open(self, transport: TransportConfig) -> WorldBridge:
        """Open the session and answer the world's frames from now on."""
        self._session = open_session(transport)
        self._session.subscribe(
            robot_key(self.fleet, self.robot_id, "sense"), SenseFrame, self._on_frame
        )
        return self

    def _on_frame(self, _key: str, frame: SenseFrame) -> None:
        if frame.robot_id != self.robot_id or self._session is None:
            return
        if frame.final:
            self.body.final.set()
            return
        setpoint = self.body.update(frame)
        if not (math.isfinite(setpoint.v_mps) and math.isfinite(setpoint.omega_radps)):
            setpoint = Twist2D(0.0, 0.0)
        self._session.publish(
            robot_key(self.fleet, self.robot_id, "cmd"),
            VelocityCommand(
                robot_id=self.robot_id,
                tick=frame.tick,
                stamp_s=frame.t_s,
                v_mps=setpoint.v_mps,
                omega_radps=setpoint.omega_radps,
            ),
        )

    def close(self) -> None:
        """Close the session (safe twice)."""
        if self._session is not None:
            self._session.close()
            self._session = None
