"""Kinematic limits and the command limiter applied after every controller.

Saturation first (|v|, |w| and both wheel speeds, scaled together so the commanded
curvature is kept), then acceleration limits against the last applied command. Both
interventions are counted: the paper attributes the tracking controller's failure to its
yaw rate leaving the 40 deg/s bound, so the counts belong in every report.
"""

from __future__ import annotations

import math

from phalanx.core.geometry import ZERO_TWIST, Twist2D
from phalanx.core.limits import KinematicLimits

_EPS = 1e-12


def _scale(v: float, w: float, limits: KinematicLimits) -> float:
    half_track_w = 0.5 * limits.track_width_m * abs(w)
    ratios = (
        limits.v_max_mps / max(abs(v), _EPS),
        limits.omega_max_radps / max(abs(w), _EPS),
        limits.wheel_v_max_mps / max(abs(v) + half_track_w, _EPS),
    )
    return min(1.0, *ratios)


def _allowed_change(current: float, wanted: float, up: float, down: float) -> float:
    speeding_up = abs(wanted) > abs(current) and wanted * current >= 0.0
    return up if speeding_up else down


def accelerate(
    current: Twist2D,
    wanted: Twist2D,
    limits: KinematicLimits,
    dt_s: float,
    *,
    emergency: bool = False,
) -> Twist2D:
    """Move from `current` towards `wanted` within the acceleration bounds over `dt_s`.

    Both axes move the same fraction of the way (a straight line in (v, w)), so a change
    between two twists of equal curvature keeps that curvature throughout: a leader
    reversing along its arc stays on it while it slows down and backs up. `emergency`
    brakes to a stop at the robot's emergency limits instead of the comfortable ones.
    """
    v, w = _accelerate(current, wanted.v_mps, wanted.omega_radps, limits, dt_s, emergency)
    return Twist2D(v, w)


def _accelerate(
    current: Twist2D,
    v: float,
    w: float,
    limits: KinematicLimits,
    dt_s: float,
    emergency: bool,
    brake_hard: bool = False,
) -> tuple[float, float]:
    dv = v - current.v_mps
    dw = w - current.omega_radps
    decel, rot = limits.decel_mps2, limits.rot_accel_radps2
    if emergency and v == 0.0 and w == 0.0:  # (a stop: `wanted == ZERO_TWIST`)
        decel = max(decel, limits.emergency_decel_mps2)
        rot = max(rot, limits.emergency_rot_decel_radps2)
    elif brake_hard:  # (slowing down at the emergency limit, turning as wanted)
        decel = max(decel, limits.emergency_decel_mps2)
    max_dv = _allowed_change(current.v_mps, v, limits.accel_mps2, decel)
    fraction = min(
        1.0,
        max_dv * dt_s / max(abs(dv), _EPS),
        rot * dt_s / max(abs(dw), _EPS),
    )
    return current.v_mps + fraction * dv, current.omega_radps + fraction * dw


class CommandLimiter:
    """Saturates and rate-limits commands; remembers the last applied one."""

    def __init__(self, limits: KinematicLimits) -> None:
        self.limits = limits
        self.saturations = 0
        self.accel_limited = 0
        self._last = ZERO_TWIST

    @property
    def last(self) -> Twist2D:
        """The last command applied (what the robot is executing now)."""
        return self._last

    def apply(
        self, command: Twist2D, dt_s: float, *, emergency: bool = False, brake_hard: bool = False
    ) -> Twist2D:
        """The command the robot may execute this step (`emergency`: a stop that cannot
        wait, braked at the robot's emergency limits; `brake_hard`: a slowdown that cannot
        wait, braked at the emergency deceleration while the turn goes on as wanted).
        """
        v, w = command.v_mps, command.omega_radps
        if not (math.isfinite(v) and math.isfinite(w)):
            v, w = 0.0, 0.0  # never forward a NaN to a motor: brake within the limits
        scale = _scale(v, w, self.limits)
        if scale < 1.0:
            self.saturations += 1
            v, w = v * scale, w * scale
        # (in floats: `accelerate`, and whether it changed the command)
        lv, lw = _accelerate(self._last, v, w, self.limits, dt_s, emergency, brake_hard)
        if lv != v or lw != w:
            self.accel_limited += 1
        self._last = Twist2D(lv, lw)
        return self._last

    def reset(self, current: Twist2D = ZERO_TWIST) -> None:
        """Start again from `current`, counters kept."""
        self._last = current
