"""Simulated positioning sensors, each seeded on its own random stream (switching one on
never changes another's draws, nor the world's sonar noise): wheel odometry with its
errors, external positioning (motion capture), and a camera reading the fiducial markers
on other robots. `SimulatedSensors` holds those a scenario's `[localisation]` asks for;
the world feeds it its robots' motion and hands each robot what reached it by now.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from phalanx.core.config import Scenario, SensorEvent
from phalanx.core.fixes import PoseFix, RelativeFix
from phalanx.core.formation import scenario_formation
from phalanx.core.localisation import LocalisationConfig
from phalanx.simulator.sensors.camera import HiddenCheck, MarkerCameraSim, Obstacles
from phalanx.simulator.sensors.mocap import MocapSim
from phalanx.simulator.sensors.odometry import WheelOdometry, arcs

FloatArray = npt.NDArray[np.float64]

__all__ = ["SimulatedSensors", "camera_mounts"]


def camera_mounts(scenario: Scenario) -> dict[str, float]:
    """Where each camera points (rad from its robot's heading): as the scenario's
    `mount_yaw_deg` says, else at the robot it follows in the formation, where that one
    sits when the shape is formed (robots that follow nobody have no camera unless
    listed in `markers.robots`).
    """
    markers = scenario.localisation.markers
    if markers is None:
        return {}
    formation = scenario_formation(scenario)
    mounts = {}
    for rid in formation.robot_ids:
        leader = formation.leader_of(rid)
        if markers.robots and rid not in markers.robots:
            continue
        if rid in markers.mount_yaw_deg:
            mounts[rid] = math.radians(markers.mount_yaw_deg[rid])
        elif leader is not None:
            slot = formation.slot_of(rid, leader)
            mounts[rid] = math.atan2(-slot.y_m, -slot.x_m)
        elif markers.robots:
            mounts[rid] = 0.0
    return mounts


def _hidden_check(events: Sequence[SensorEvent]) -> HiddenCheck:
    hides = [e for e in events if e.kind == "markers_hidden"]

    def hidden(robot_id: str, t_s: float) -> bool:
        return any(
            (not e.robots or robot_id in e.robots) and e.start_s <= t_s < e.start_s + e.duration_s
            for e in hides
        )

    return hidden


class SimulatedSensors:
    """The positioning sensors of one world's robots."""

    def __init__(
        self,
        config: LocalisationConfig,
        *,
        track_m: float,
        robot_radius_m: float,
        seed: int,
        obstacles: Obstacles,
        mounts_rad: dict[str, float],
        events: Sequence[SensorEvent] = (),
    ) -> None:
        self.config = config
        self.odometry: WheelOdometry | None = None
        if config.odometry.any:
            self.odometry = WheelOdometry(config.odometry, track_m=track_m, seed=seed)
        self.mocap = MocapSim(config.mocap, seed=seed) if config.mocap else None
        self.camera: MarkerCameraSim | None = None
        if config.markers is not None:
            self.camera = MarkerCameraSim(
                config.markers,
                seed=seed,
                robot_radius_m=robot_radius_m,
                obstacles=obstacles,
                mounts_rad=mounts_rad,
                hidden=_hidden_check(events),
            )

    @property
    def active(self) -> bool:
        """Whether any sensor is simulated at all."""
        return self.odometry is not None or self.mocap is not None or self.camera is not None

    def add_robot(self, robot_id: str, x_m: float, y_m: float, theta_rad: float) -> None:
        """A robot placed in the world at this pose."""
        if self.odometry is not None:
            self.odometry.add_robot(x_m, y_m, theta_rad)
        if self.mocap is not None:
            self.mocap.add_robot(robot_id)
        if self.camera is not None:
            self.camera.add_robot(robot_id)

    def substep(self, t0_s: float, dt_s: float, before: FloatArray, after: FloatArray) -> None:
        """The robots moved from `before` to `after` (n x 3 poses) over (t0, t0 + dt]."""
        if self.mocap is not None:
            self.mocap.sample(t0_s, dt_s, before, after)
        if self.camera is not None:
            self.camera.sample(t0_s, dt_s, before, after)

    def odometry_step(self, before: FloatArray, after: FloatArray) -> FloatArray:
        """Every robot's odometry pose (n x 3) after a control step from `before` to `after`."""
        assert self.odometry is not None  # noqa: S101 - the world asks only when it has one
        ds, dth = arcs(
            before[:, 0], before[:, 1], before[:, 2], after[:, 0], after[:, 1], after[:, 2]
        )
        return self.odometry.step(ds, dth)

    def take(self, index: int, now_s: float) -> tuple[tuple[PoseFix, ...], tuple[RelativeFix, ...]]:
        """Robot `index`'s fixes and relative measurements that have arrived by `now_s`."""
        fixes = self.mocap.take(index, now_s) if self.mocap is not None else ()
        relative = self.camera.take(index, now_s) if self.camera is not None else ()
        return fixes, relative
