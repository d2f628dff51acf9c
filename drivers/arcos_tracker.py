"""What a P3DX's packets say, for the `arcos` driver: SIPs into odometry, sonar, bumpers,
battery and motor state; the CONFIG packet into the robot's own limits. No I/O and no
lock: the driver calls it with its lock held.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from phalanx.core.errors import ProtocolError
from phalanx.core.geometry import Pose2D, Twist2D, wrap_angle
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.protocols.arcos import (
    CONFIG_PAC,
    SIP_MOVING,
    SIP_STOPPED,
    ConvFactors,
    RobotConfig,
    Sip,
    decode_config,
    decode_sip,
    wrap_delta,
)

N_SONARS = 16
FRAME_OVERHEAD_BYTES = 5  # FA FB, the length byte, the two checksum bytes


@dataclass
class ArcosStats:
    """Counters of the link; `*_s` are monotonic times of the latest such event."""

    sips: int = 0
    bad_sips: int = 0
    other_frames: int = 0
    reconnects: int = 0
    reconnect_failures: int = 0
    links_lost: int = 0
    commands_sent: int = 0
    sips_lost_s: float | None = None  # SIPs declared lost
    loss_stop_s: float | None = None  # the STOP sent for it (None: the link was gone)


class SipTracker:
    """The robot's latest readings, from its SIPs and CONFIG packet."""

    def __init__(self, stats: ArcosStats) -> None:
        self.stats = stats
        self.factors = ConvFactors()  # set from the SYNC2 reply's subtype
        self.config: RobotConfig | None = None
        self.sip: Sip | None = None
        self.odometry: Odometry | None = None
        self.sonar_m: tuple[float, ...] = (5.0,) * N_SONARS
        self.last_sip_s = time.monotonic()
        self._pose = Pose2D(0.0, 0.0, 0.0)
        self._last_xy: tuple[int, int] | None = None
        self._th0: float | None = None

    def new_session(self) -> None:
        """A new connection: position counters restart, the integrated pose carries on."""
        self._last_xy, self._th0 = None, None
        self.last_sip_s = time.monotonic()

    def take(self, body: bytes, *, byte_time_s: float) -> Sip | None:
        """Account for one frame's body; the SIP if it was a good one.

        A SIP is stamped when the robot sent it: its arrival less its time on the wire
        (the whole frame at `byte_time_s` a byte).
        """
        kind = body[0]
        if kind in (SIP_STOPPED, SIP_MOVING):
            try:
                sip = decode_sip(body)
            except ProtocolError:
                self.stats.bad_sips += 1
                return None
            wire_s = (len(body) + FRAME_OVERHEAD_BYTES) * byte_time_s
            self._on_sip(sip, time.monotonic() - wire_s)
            return sip
        if kind == CONFIG_PAC:
            try:
                self.config = decode_config(body)
            except ProtocolError:
                self.stats.bad_sips += 1
        else:
            self.stats.other_frames += 1
        return None

    def status(self, *, link_fault: str, estop: str) -> RobotStatus:
        """Sonar (m), bumpers, battery (V) and motor state of the latest SIP, with the
        driver's link fault and E-stop latch folded in.
        """
        faults: tuple[str, ...] = (link_fault,) if link_fault else ()
        sip = self.sip
        if sip is None:
            return RobotStatus(faults=faults or ("no SIP yet",), estopped=bool(estop))
        if sip.fault_flags:
            faults += (f"firmware fault flags {sip.fault_flags:#06x}",)
        return RobotStatus(
            sonar_ranges_m=self.sonar_m,
            bumpers=sip.bumpers,
            battery_v=sip.battery_v,
            motors_enabled=sip.motors_enabled and not link_fault and not estop,
            estopped=sip.estopped or bool(estop),
            stalled=sip.left_stall or sip.right_stall,
            faults=faults,
        )

    def _on_sip(self, sip: Sip, measured_s: float) -> None:
        f = self.factors
        th = wrap_angle(sip.th * f.angle_rad)
        if self._last_xy is None or self._th0 is None:
            self._th0 = wrap_angle(th - self._pose.theta_rad)
            self._last_xy = (sip.x, sip.y)
        dx_mm = wrap_delta(sip.x, self._last_xy[0]) * f.dist_mm
        dy_mm = wrap_delta(sip.y, self._last_xy[1]) * f.dist_mm
        self._last_xy = (sip.x, sip.y)
        # ARCOS integrates x, y in its own frame; ours starts at the first SIP's pose.
        c, s = math.cos(-self._th0), math.sin(-self._th0)
        pose = Pose2D(
            self._pose.x_m + (c * dx_mm - s * dy_mm) / 1000.0,
            self._pose.y_m + (s * dx_mm + c * dy_mm) / 1000.0,
            wrap_angle(th - self._th0),
        )
        v = (sip.left_vel + sip.right_vel) / 2.0 * f.vel_mmps / 1000.0
        if sip.rot_vel_x10 is not None:  # the firmware's own yaw rate (ArRobot does the same)
            w = math.radians(sip.rot_vel_x10 / 10.0)
        else:
            w = (sip.right_vel - sip.left_vel) / 2.0 * f.vel_mmps * f.diff
        self._pose = pose
        self.odometry = Odometry(pose, Twist2D(v, w), measured_s)
        ranges = list(self.sonar_m)
        for index, range_raw in sip.sonars:
            if 0 <= index < N_SONARS:
                ranges[index] = range_raw * f.range_mm / 1000.0
        self.sonar_m = tuple(ranges)
        self.sip = sip
        self.last_sip_s = time.monotonic()
        self.stats.sips += 1
