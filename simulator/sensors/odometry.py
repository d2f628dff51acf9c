"""Wheel odometry with the errors a real differential-drive robot's has, for every robot of
the world at once (numpy arrays, one entry per robot).

Per wheel: a scale error drawn once per robot (a tyre a little larger or softer than
nominal), a random walk (travel error whose variance grows with the distance the wheel
rolls), and now and then a slip (the wheel loses part of a step's travel). The robot's
true motion over a step is split into its wheels' travel, each wheel's travel corrupted,
and the corrupted travel integrated into the odometry pose: with no error configured the
odometry is the truth.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from phalanx.core.localisation import OdometryErrors
from phalanx.simulator.kinematics import integrate_arcs

FloatArray = npt.NDArray[np.float64]


def arcs(
    x0: FloatArray, y0: FloatArray, th0: FloatArray, x1: FloatArray, y1: FloatArray, th1: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The arcs (signed length m, turn rad) taking each pose 0 to its pose 1."""
    dth = np.mod(th1 - th0 + np.pi, 2 * np.pi) - np.pi
    c, s = np.cos(th0), np.sin(th0)
    bx = c * (x1 - x0) + s * (y1 - y0)
    by = -s * (x1 - x0) + c * (y1 - y0)
    half = 0.5 * dth
    safe = np.where(np.abs(half) > 1e-9, half, 1.0)
    stretch = np.where(np.abs(half) > 1e-9, half / np.sin(safe), 1.0)
    return np.sign(bx + 0.0) * np.hypot(bx, by) * stretch, dth


class WheelOdometry:
    """Every robot's odometry pose under `errors`, seeded."""

    def __init__(self, errors: OdometryErrors, *, track_m: float, seed: int) -> None:
        self.errors, self.track_m = errors, track_m
        self.rng = np.random.default_rng([seed, 0x0D0])
        self.scale = np.zeros((0, 2))
        self.pose = np.zeros((0, 3))

    def add_robot(self, x_m: float, y_m: float, theta_rad: float) -> None:
        """A robot whose odometry starts at this pose (its scale errors drawn now)."""
        drawn = self.rng.normal(0.0, self.errors.scale_std_frac, 2)
        self.scale = np.vstack([self.scale, drawn])
        self.pose = np.vstack([self.pose, [x_m, y_m, theta_rad]])

    def step(self, ds_m: FloatArray, dth_rad: FloatArray) -> FloatArray:
        """Move every robot's odometry by its true arc (`ds_m`, `dth_rad`) as its wheels
        measure it; the odometry poses (n x 3).
        """
        e, half_track = self.errors, 0.5 * self.track_m
        wheels = np.column_stack([ds_m - half_track * dth_rad, ds_m + half_track * dth_rad])
        travel = np.abs(wheels)
        measured = wheels * (1.0 + self.scale)
        if e.walk_std_m > 0.0:
            measured += self.rng.normal(0.0, 1.0, wheels.shape) * e.walk_std_m * np.sqrt(travel)
        if e.slip_per_m > 0.0:
            slips = self.rng.random(wheels.shape) < e.slip_per_m * travel
            loss = self.rng.uniform(0.0, e.slip_max_frac, wheels.shape)
            measured = np.where(slips, measured * (1.0 - loss), measured)
        ds = 0.5 * (measured[:, 0] + measured[:, 1])
        dth = (measured[:, 1] - measured[:, 0]) / self.track_m
        x, y, th = integrate_arcs(self.pose[:, 0], self.pose[:, 1], self.pose[:, 2], ds, dth, 1.0)
        self.pose = np.column_stack([x, y, th])
        return self.pose


class OdometryTracker:
    """One robot's odometry under `errors`, fed its true pose whenever it is read (the
    ARCOS emulator, at each SIP): the true motion since the last reading, as the wheels
    measure it, integrated from the start pose.
    """

    def __init__(
        self,
        errors: OdometryErrors,
        *,
        track_m: float,
        seed: int,
        start: tuple[float, float, float],
    ) -> None:
        self.wheels = WheelOdometry(errors, track_m=track_m, seed=seed)
        self.wheels.add_robot(*start)
        self._truth = np.array([start], dtype=np.float64)

    def report(self, x_m: float, y_m: float, theta_rad: float) -> tuple[float, float, float]:
        """The odometry pose (m, m, rad) when the robot truly is at (x, y, theta)."""
        now = np.array([[x_m, y_m, theta_rad]], dtype=np.float64)
        t0, t1 = self._truth, now
        ds, dth = arcs(t0[:, 0], t0[:, 1], t0[:, 2], t1[:, 0], t1[:, 1], t1[:, 2])
        self._truth = now
        pose = self.wheels.step(ds, dth)[0]
        return float(pose[0]), float(pose[1]), float(pose[2])
