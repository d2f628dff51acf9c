"""P3DX kinematics as plain vectorised functions (IR-SIM style): limits and exact arcs.

Arrays hold one entry per robot. The robot's physical limits come from its parameter
file; a controller's own (possibly tighter) limits are applied in the agent.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from phalanx.core.config import RobotParams

FloatArray = npt.NDArray[np.float64]
_SMALL_OMEGA_RADPS = 1e-9


def _towards(current: FloatArray, wanted: FloatArray, up: float, down: float) -> FloatArray:
    speeding_up = (np.abs(wanted) > np.abs(current)) & (wanted * current >= 0.0)
    limit = np.where(speeding_up, up, down)
    return current + np.clip(wanted - current, -limit, limit)


def apply_robot_limits(
    v: FloatArray,
    w: FloatArray,
    v_cmd: FloatArray,
    w_cmd: FloatArray,
    robot: RobotParams,
    dt_s: float,
) -> tuple[FloatArray, FloatArray]:
    """Velocities after `dt_s` of chasing the commands within the robot's physical limits.

    Saturation scales v and w together (keeps the curvature) to respect |v|, |w| and
    each wheel's speed; then acceleration limits move from the current velocities.
    """
    half_track = 0.5 * robot.track_width_m
    eps = 1e-12
    scale = np.minimum.reduce(
        [
            np.ones_like(v_cmd),
            robot.v_max_mps / np.maximum(np.abs(v_cmd), eps),
            robot.omega_max_radps / np.maximum(np.abs(w_cmd), eps),
            robot.wheel_v_max_mps / np.maximum(np.abs(v_cmd) + half_track * np.abs(w_cmd), eps),
        ]
    )
    v_new = _towards(v, v_cmd * scale, robot.accel_mps2 * dt_s, robot.decel_mps2 * dt_s)
    rot = robot.rot_accel_radps2 * dt_s
    w_new = _towards(w, w_cmd * scale, rot, rot)
    return v_new, w_new


def integrate_arcs(
    x: FloatArray, y: FloatArray, th: FloatArray, v: FloatArray, w: FloatArray, dt_s: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Exact unicycle motion of every robot for `dt_s` at constant (v, w)."""
    th_new = th + w * dt_s
    straight = np.abs(w) < _SMALL_OMEGA_RADPS
    safe_w = np.where(straight, 1.0, w)
    radius = v / safe_w
    mid = th + 0.5 * w * dt_s
    x_new = np.where(
        straight, x + v * dt_s * np.cos(mid), x + radius * (np.sin(th_new) - np.sin(th))
    )
    y_new = np.where(
        straight, y + v * dt_s * np.sin(mid), y - radius * (np.cos(th_new) - np.cos(th))
    )
    return x_new, y_new, (th_new + math.pi) % (2 * math.pi) - math.pi
