"""The motion side of P3DX firmware, for the ARCOS emulator: what each motion command does
and the velocity profile the wheels follow.

ARCOS (Pioneer 3 operations manual, "Robots in motion"; AMRISim's `EmulatePioneer.cc`
for the simulated counterpart) runs translation and rotation as two channels, each either
at a velocity (VEL, RVEL/ROTATE; VEL2 is recomposed into the two) or to a position
(MOVE: a distance along the heading it had; HEAD/DHEAD: an absolute or relative heading in
the odometry frame), always within the working maxima (SETV, SETRV) and ramped at the
working accelerations and decelerations (SETA, SETRA: positive sets the acceleration,
negative the deceleration), each capped at the CONFIG packet's "top" values. STOP brings
both channels to rest at the deceleration; E_STOP overrides it and brakes at the tops, and
motion commands are ignored until the robot is at rest (AMRISim does the same; the
emulated firmware, like AMRISim's, does not latch it: the driver does). Units inside:
mm, deg, s (the protocol's), converted to SI only for the body.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from phalanx.core.geometry import Pose2D, Twist2D, wrap_angle
from phalanx.core.robot_params import RobotParams

MOVE_DONE_MM = 1.0  # a MOVE is done this close to its end
HEAD_DONE_DEG = 0.2  # a HEAD/DHEAD is done this close to its heading


@dataclass(frozen=True)
class FirmwareLimits:
    """The firmware's working maxima and (de)accelerations and the tops that cap them.

    Mm/s, deg/s, mm/s², deg/s². The working values start as the robot file's ratings
    (`configs/robots/p3dx.toml`) and change with SETV, SETRV, SETA and SETRA.
    """

    trans_vel_max: float
    rot_vel_max: float
    trans_accel: float
    trans_decel: float
    rot_accel: float
    rot_decel: float
    trans_vel_top: float
    rot_vel_top: float
    trans_accel_top: float
    rot_accel_top: float

    @classmethod
    def of(
        cls, robot: RobotParams, *, trans_accel_top: float, rot_accel_top: float
    ) -> FirmwareLimits:
        """A robot's rated limits as the firmware's maxima; braking capability as the tops."""
        return cls(
            trans_vel_max=robot.v_max_mps * 1000.0,
            rot_vel_max=robot.omega_max_degps,
            trans_accel=robot.accel_mps2 * 1000.0,
            trans_decel=robot.decel_mps2 * 1000.0,
            rot_accel=robot.rot_accel_degps2,
            rot_decel=robot.rot_accel_degps2,
            trans_vel_top=robot.v_max_mps * 1000.0,
            rot_vel_top=robot.omega_max_degps,
            trans_accel_top=max(trans_accel_top, robot.accel_mps2 * 1000.0),
            rot_accel_top=max(rot_accel_top, robot.rot_accel_degps2),
        )

    def body_params(self, robot: RobotParams) -> RobotParams:
        """`robot` able to follow any profile within the tops (the firmware ramps, not the
        body): accelerations at the tops.
        """
        return robot.model_copy(
            update={
                "accel_mps2": self.trans_accel_top / 1000.0,
                "decel_mps2": self.trans_accel_top / 1000.0,
                "rot_accel_degps2": self.rot_accel_top,
            }
        )


def _towards(value: float, target: float, up: float, down: float, dt_s: float) -> float:
    """`value` moved towards `target`: at `up` per second while speeding up in the same
    direction, at `down` while slowing down or reversing (through zero at `down`).
    """
    speeding_up = value * target >= 0 and abs(target) > abs(value)
    step = (up if speeding_up else down) * dt_s
    return value + max(-step, min(step, target - value))


def _braking_speed(remaining: float, decel: float, cap: float) -> float:
    """The signed speed from which `decel` stops exactly `remaining` ahead, within `cap`."""
    # Aimed at 80 % of `decel`: the ramp (at `decel`) then keeps up with the curve.
    return math.copysign(min(cap, math.sqrt(1.6 * decel * abs(remaining))), remaining)


class Motion:
    """Both motion channels of the firmware and the profile they generate. Not locked:
    the emulator calls it with its own lock held.
    """

    def __init__(self, limits: FirmwareLimits, *, diff_conv: float, vel2_divisor: float) -> None:
        self.limits = limits
        self.diff_conv = diff_conv  # (right - left) / 2 * diff_conv = rad/s
        self.vel2_divisor = vel2_divisor
        self.v_mmps = 0.0  # the profile: what the wheels are told now
        self.w_degps = 0.0
        self.estopping = False
        self.held = False  # the watchdog's stop: targets kept, motion paused
        self._trans: tuple[str, float, Pose2D | None] = ("vel", 0.0, None)
        self._rot: tuple[str, float] = ("vel", 0.0)

    # -- commands --------------------------------------------------------------------

    def vel(self, mmps: float) -> None:
        """VEL: translate at `mmps` (capped at the working maximum)."""
        if not self.estopping:
            self._trans = ("vel", mmps, None)

    def rvel(self, degps: float) -> None:
        """RVEL / ROTATE: rotate at `degps`, counter-clockwise positive."""
        if not self.estopping:
            self._rot = ("vel", degps)

    def vel2(self, left: int, right: int) -> None:
        """VEL2: wheel speeds in Vel2Divisor units, recomposed into VEL and RVEL."""
        left_mmps, right_mmps = left * self.vel2_divisor, right * self.vel2_divisor
        self.vel((left_mmps + right_mmps) / 2.0)
        self.rvel(math.degrees((right_mmps - left_mmps) / 2.0 * self.diff_conv))

    def move(self, mm: float, pose: Pose2D) -> None:
        """MOVE: `mm` along the current heading (negative: backwards), then stop."""
        if not self.estopping:
            self._trans = ("move", mm, pose)

    def head(self, deg: float) -> None:
        """HEAD: turn to `deg` in the odometry frame, the short way round."""
        if not self.estopping:
            self._rot = ("head", math.radians(deg))

    def dhead(self, deg: float, pose: Pose2D) -> None:
        """DHEAD: turn by `deg` from the current heading."""
        if not self.estopping:
            self._rot = ("head", wrap_angle(pose.theta_rad + math.radians(deg)))

    def stop(self) -> None:
        """STOP: both channels to rest at the working decelerations."""
        if not self.estopping:
            self._trans, self._rot = ("vel", 0.0, None), ("vel", 0.0)

    def estop(self) -> None:
        """E_STOP: both channels to rest at the tops; motion ignored until at rest."""
        self.stop()
        self.estopping = True

    def set_limit(self, name: str, value: float) -> None:
        """SETV / SETRV / SETA / SETRA: a working value, capped at its top (0 ignored)."""
        if value <= 0:
            return
        top = {
            "trans_vel_max": self.limits.trans_vel_top,
            "rot_vel_max": self.limits.rot_vel_top,
            "trans_accel": self.limits.trans_accel_top,
            "trans_decel": self.limits.trans_accel_top,
            "rot_accel": self.limits.rot_accel_top,
            "rot_decel": self.limits.rot_accel_top,
        }[name]
        self.limits = replace(self.limits, **{name: min(value, top)})

    # -- the profile -----------------------------------------------------------------

    @property
    def target(self) -> Twist2D:
        """What the profile is heading for now (m/s, rad/s): zero while stopping or held."""
        v_mmps, w_degps = self._targets(None)
        return Twist2D(v_mmps / 1000.0, math.radians(w_degps))

    @property
    def busy(self) -> bool:
        """Whether the profile is changing (ramping, or driving to a position)."""
        targets = self._targets(None)
        return (
            self._trans[0] != "vel"
            or self._rot[0] != "vel"
            or (self.v_mmps, self.w_degps) != targets
        )

    def step(self, dt_s: float, pose: Pose2D) -> Twist2D:
        """Advance the profile `dt_s` (the body at odometry `pose`); the wheels' command."""
        lim = self.limits
        target_v, target_w = self._targets(pose)
        if self.estopping:
            up_v = down_v = lim.trans_accel_top
            up_w = down_w = lim.rot_accel_top
        else:
            up_v, down_v, up_w, down_w = (
                lim.trans_accel, lim.trans_decel, lim.rot_accel, lim.rot_decel,
            )  # fmt: skip
        self.v_mmps = _towards(self.v_mmps, target_v, up_v, down_v, dt_s)
        self.w_degps = _towards(self.w_degps, target_w, up_w, down_w, dt_s)
        if self.estopping and self.v_mmps == 0.0 and self.w_degps == 0.0:
            self.estopping = False
        return Twist2D(self.v_mmps / 1000.0, math.radians(self.w_degps))

    def _targets(self, pose: Pose2D | None) -> tuple[float, float]:
        if self.held or self.estopping:
            return 0.0, 0.0
        return self._trans_target(pose), self._rot_target(pose)

    def _trans_target(self, pose: Pose2D | None) -> float:
        lim = self.limits
        mode, value, start = self._trans
        if mode == "vel":
            return max(-lim.trans_vel_max, min(lim.trans_vel_max, value))
        if pose is None or start is None:
            return self.v_mmps
        travelled = (
            (pose.x_m - start.x_m) * math.cos(start.theta_rad)
            + (pose.y_m - start.y_m) * math.sin(start.theta_rad)
        ) * 1000.0
        remaining = value - travelled
        if abs(remaining) < MOVE_DONE_MM or remaining * value < 0:
            self._trans = ("vel", 0.0, None)
            return 0.0
        return _braking_speed(remaining, lim.trans_decel, lim.trans_vel_max)

    def _rot_target(self, pose: Pose2D | None) -> float:
        lim = self.limits
        mode, value = self._rot
        if mode == "vel":
            return max(-lim.rot_vel_max, min(lim.rot_vel_max, value))
        if pose is None:
            return self.w_degps
        error = math.degrees(wrap_angle(value - pose.theta_rad))
        if abs(error) < HEAD_DONE_DEG:
            self._rot = ("vel", 0.0)
            return 0.0
        return _braking_speed(error, lim.rot_decel, lim.rot_vel_max)
