"""`phalanx mocap`: a motion-capture system's rigid bodies as pose fixes on the fleet.

It reads the system through the `motioncapture` library (libmotioncapture's Python
bindings: OptiTrack, Vicon, Qualisys, VRPN, and a mock backend; what Crazyswarm2 uses),
maps rigid-body names to robot ids (the scenario's `[localisation.mocap] bodies`, or
`--body NAME=ROBOT`), turns each body's pose into the fleet's world frame (the mocap
frame's origin and yaw in the world, `--origin`), and publishes a `PoseFixMessage` per
tracked robot and frame on `phalanx/<fleet>/robot/<id>/fix`, stamped with the Unix time
the frame was taken (received, less the system's `latency_s`). A body the system lost
(non-finite pose) is skipped and counted; so is one the map does not name.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from phalanx.core.errors import DriverUnavailable
from phalanx.core.geometry import Pose2D
from phalanx.runtime.signals import Stoppable
from phalanx.wire.keys import robot_key
from phalanx.wire.positions import PoseFixMessage
from phalanx.wire.transport import FleetSession

log = logging.getLogger("phalanx.mocap")


def yaw_of(w: float, x: float, y: float, z: float) -> float:
    """The heading (rotation about the vertical, rad) of a unit quaternion (w, x, y, z)."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


@dataclass
class MocapOptions:
    """What the bridge reads and how it publishes."""

    system: str  # motioncapture's backend: optitrack, vicon, qualisys, vrpn, mock, ...
    settings: dict[str, str]  # the backend's own (hostname, rigid_bodies for mock, ...)
    bodies: dict[str, str]  # rigid-body name -> robot id
    std_m: float
    std_rad: float
    latency_s: float = 0.0
    origin: Pose2D = field(default_factory=lambda: Pose2D(0.0, 0.0, 0.0))


@dataclass
class MocapStats:
    """Frames read, fixes published, bodies skipped (lost or not in the map)."""

    frames: int = 0
    published: int = 0
    lost: int = 0
    unmapped: int = 0


class MocapBridge:
    """Reads the motion-capture system and publishes fixes until stopped."""

    def __init__(self, options: MocapOptions, fleet: str) -> None:
        self.options, self.fleet = options, fleet
        self.stats = MocapStats()
        self._system: Any = None

    def connect(self) -> None:
        """Connect to the motion-capture system."""
        try:
            import motioncapture
        except ImportError as exc:
            raise DriverUnavailable(
                "the mocap bridge needs the motioncapture library: pip install 'phalanx[sensing]'"
            ) from exc
        try:
            self._system = motioncapture.connect(self.options.system, dict(self.options.settings))
        except RuntimeError as exc:
            raise DriverUnavailable(
                f"motion capture {self.options.system!r} with {self.options.settings}: {exc}"
            ) from exc

    def run(self, session: FleetSession, stop: Stoppable, *, duration_s: float = math.inf) -> None:
        """Publish every frame's fixes until `stop` (or `duration_s`)."""
        if self._system is None:
            self.connect()
        ends = time.monotonic() + duration_s
        while not stop.is_set() and time.monotonic() < ends:
            self._system.waitForNextFrame()
            stamp_s = time.time() - self.options.latency_s
            self.stats.frames += 1
            for name, body in self._system.rigidBodies.items():
                self._publish(session, name, body, stamp_s)

    def _publish(self, session: FleetSession, name: str, body: Any, stamp_s: float) -> None:
        robot = self.options.bodies.get(name)
        if robot is None:
            self.stats.unmapped += 1
            return
        pose = self.world_pose(body.position, body.rotation)
        if pose is None:
            self.stats.lost += 1
            return
        message = PoseFixMessage(
            robot_id=robot, stamp_s=stamp_s, x_m=pose.x_m, y_m=pose.y_m,
            theta_rad=pose.theta_rad, std_m=self.options.std_m, std_rad=self.options.std_rad,
        )  # fmt: skip
        session.publish(robot_key(self.fleet, robot, "fix"), message)
        self.stats.published += 1

    def world_pose(self, position: Any, rotation: Any) -> Pose2D | None:
        """A body's pose in the fleet's world frame (None if the system lost it)."""
        x, y = float(position[0]), float(position[1])
        yaw = yaw_of(float(rotation.w), float(rotation.x), float(rotation.y), float(rotation.z))
        if not all(math.isfinite(v) for v in (x, y, yaw)):
            return None
        return self.options.origin.compose(Pose2D(x, y, yaw))


def body_map(
    scenario_bodies: Mapping[str, str], robots: tuple[str, ...], extra: list[str]
) -> dict[str, str]:
    """Rigid-body name -> robot id: every robot under its own id, then the scenario's
    `bodies`, then `NAME=ROBOT` pairs from the command line.
    """
    out = {rid: rid for rid in robots}
    for name, robot in scenario_bodies.items():
        out.pop(robot, None)
        out[name] = robot
    for pair in extra:
        name, sep, robot = pair.partition("=")
        if not sep or robot not in robots:
            raise ValueError(f"--body {pair!r}: expected NAME=ROBOT with ROBOT one of {robots}")
        out[name] = robot
    return out
