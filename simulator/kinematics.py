"""P3DX kinematics as plain vectorised functions (IR-SIM style): limits and exact arcs.

Arrays hold one entry per robot. The robot's physical limits come from its parameter
file; a controller's own (possibly tighter) limits are applied in the agent.

A fleet of up to `SCALAR_MAX` robots is cheaper to step in plain floats than in numpy
(a numpy call costs about a microsecond whatever its size): `limits_and_arcs_scalar`
does the same arithmetic, operation for operation, and gives the same numbers
(`tests/unit/test_world_batched.py` pins both paths against each other).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from phalanx.core.robot_params import RobotParams

FloatArray = npt.NDArray[np.float64]
_SMALL_OMEGA_RADPS = 1e-9
SCALAR_MAX = 12
_TWO_PI = 2 * math.pi


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


def _towards_scalar(current: float, wanted: float, up: float, down: float) -> float:
    limit = up if abs(wanted) > abs(current) and wanted * current >= 0.0 else down
    step = wanted - current
    # numpy's clip: max(step, lo) then min(., hi), each keeping the first on a tie
    step = step if step > -limit else -limit
    return current + (step if step < limit else limit)


def limits_and_arcs_scalar(
    state: tuple[FloatArray, ...], robot: RobotParams, dt_s: float, *, substeps: int = 1
) -> tuple[FloatArray, ...]:
    """`apply_robot_limits` then `integrate_arcs` over `(x, y, th, v, w, v_cmd, w_cmd)`
    in plain floats, robot by robot, `substeps` times in a row (sub-steps of `dt_s` each,
    nothing in between: no contact can happen, see `Contacts.none_within`): `(v, w, x,
    y, th)` after them.
    """
    half_track, eps = 0.5 * robot.track_width_m, 1e-12
    up, down, rot = robot.accel_mps2 * dt_s, robot.decel_mps2 * dt_s, robot.rot_accel_radps2 * dt_s
    v_max, w_max, wheel_max = robot.v_max_mps, robot.omega_max_radps, robot.wheel_v_max_mps
    vs, ws, xs, ys, ths = [], [], [], [], []
    for x, y, th, v, w, vc, wc in zip(*(a.tolist() for a in state), strict=True):
        scale = min(
            1.0,
            v_max / max(abs(vc), eps),
            w_max / max(abs(wc), eps),
            wheel_max / max(abs(vc) + half_track * abs(wc), eps),
        )
        v_want, w_want = vc * scale, wc * scale
        for _ in range(substeps):
            v = _towards_scalar(v, v_want, up, down)
            w = _towards_scalar(w, w_want, rot, rot)
            x, y, th = _arc_scalar(x, y, th, v, w, dt_s)
        vs.append(v)
        ws.append(w)
        xs.append(x)
        ys.append(y)
        ths.append(th)
    return tuple(np.array(column, dtype=np.float64) for column in (vs, ws, xs, ys, ths))


def _arc_scalar(
    x: float, y: float, th: float, v: float, w: float, dt_s: float
) -> tuple[float, float, float]:
    """`integrate_arcs` of one robot in floats, operation for operation."""
    th_new = th + w * dt_s
    if abs(w) < _SMALL_OMEGA_RADPS:
        mid = th + 0.5 * w * dt_s
        x, y = x + v * dt_s * math.cos(mid), y + v * dt_s * math.sin(mid)
    else:
        radius = v / w
        x = x + radius * (math.sin(th_new) - math.sin(th))
        y = y - radius * (math.cos(th_new) - math.cos(th))
    return x, y, (th_new + math.pi) % _TWO_PI - math.pi
