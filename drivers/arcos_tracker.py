"""What a P3DX's packets say, for the `arcos` driver: SIPs into odometry, sonar, bumpers,
battery and motor state; the CONFIG packet into the robot's own limits; a simulator's
SIMSTAT into the robot's true pose. No I/O and no lock: the driver calls it with its lock
held.

A simulator reports headings coarser than the protocol carries: AMRISim (and MobileSim)
round the heading to a whole degree, in SIPs and SIMSTATs alike, which puts a slot 1 m
away up to 9 mm off. `QuantisedHeading` follows such a heading finer, from the yaw rate
the same packets report (see its docstring).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from phalanx.core.errors import ProtocolError
from phalanx.core.geometry import Pose2D, Twist2D, wrap_angle
from phalanx.core.robot import Odometry, RobotStatus, TruePose
from phalanx.protocols.arcos import (
    CONFIG_PAC,
    SIMSTAT,
    SIP_MOVING,
    SIP_STOPPED,
    ConvFactors,
    RobotConfig,
    SimStat,
    Sip,
    decode_config,
    decode_simstat,
    decode_sip,
    wrap_delta,
)

N_SONARS = 16
# A chord driven this long, turning at most this much along it, gives a heading (from
# positions in whole or half millimetres: within 0.1 deg).
CHORD_M = 0.5
CHORD_TURN_RAD = math.radians(10.0)
# A chord's correction is eased in over about this long (s), not put in at once: a
# heading that jumps moves every slot behind the robot sideways at once (0.2 deg: 7 mm
# two metres back), and a follower chases that jump.
CHORD_EASE_S = 1.0
# Slower than this (m/s), a robot is taken to stand: its chords are too short to tell.
MOVING_MPS = 0.02
FRAME_OVERHEAD_BYTES = 5  # FA FB, the length byte, the two checksum bytes
# A robot's cycle may run this much longer than it says (its clock against ours) and its
# packets' stamps still follow their arrivals when they come on time.
CYCLE_SLACK = 0.005


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


class CycleClock:
    """When the robot sent its packets, from when they arrived.

    The firmware sends a SIP every cycle (CONFIG's SipCycle: 100 ms on a P3DX); a
    simulator sends a SIMSTAT just before it, saying how long its last update took in
    real time. A packet was sent no later than it arrived, nor more than a cycle after
    the one before it: its stamp is the earlier of the two. A reader the host held up
    (a loaded machine: tens of milliseconds, then the packets read in one burst) so
    stamps them when the robot sent them, not when it got round to them, and robots
    recorded side by side stay in step; a packet on time is stamped at its arrival. After
    a frame was lost, or on a new connection, `lose()` forgets the last stamp: the next
    packet may come more than a cycle later.
    """

    def __init__(self) -> None:
        self.last_s: float | None = None

    def stamp(self, arrived_s: float, period_s: float) -> float:
        """When the packet that arrived at `arrived_s` was sent, `period_s` (0: not
        known) being the robot's cycle since the one before.
        """
        sent_s = arrived_s
        if self.last_s is not None and period_s > 0.0:
            sent_s = min(arrived_s, self.last_s + period_s * (1.0 + CYCLE_SLACK))
        self.last_s = sent_s
        return sent_s

    def lose(self) -> None:
        """The next packet may not follow the last by one cycle."""
        self.last_s = None


class QuantisedHeading:
    """A heading reported in steps of `step_rad`, followed finer than the steps.

    Between reports the yaw rate is integrated (trapezoidal); when the report moves into
    another step, the heading crossed that step's edge somewhere between the two reports
    (at half-way on average), so it is put on the edge plus half the interval's turn;
    either way it is held inside the step the report allows. Turning at the paper's
    3 deg/s with 100 ms reports, that is within 0.15 deg of the truth, where the whole
    degree alone is within 0.5.

    Positions come finer (a millimetre, or half of one): given them, every CHORD_M of a
    drive that turns little along it, the heading is set right by the chord's direction
    (a wheeled robot goes where it heads), which is the heading half-way along the arc:
    within 0.1 deg, also on a long straight reverse, where no edge is crossed. That
    correction is eased in (CHORD_EASE_S), so the heading never jumps by it.
    """

    def __init__(self, step_rad: float) -> None:
        self.step_rad = step_rad
        self._step: int | None = None  # the reported step, in steps
        self._heading = 0.0  # unwrapped, rad
        self._rate_radps = 0.0
        self._t_s = 0.0
        self._anchor: tuple[float, float, float, int] | None = None  # x, y, heading, way
        self._easing = 0.0  # rad of chord correction still to put in

    def update(
        self,
        reported_rad: float,
        rate_radps: float,
        t_s: float,
        *,
        position: tuple[float, float] | None = None,
        way: int = 0,
    ) -> float:
        """The heading (rad, wrapped) at `t_s`, reported as `reported_rad` while turning
        at `rate_radps`; `position` (m, in the heading's frame) and `way` (+1 driving
        forwards, -1 backwards, 0 standing) let chords correct it.
        """
        step = self.step_rad
        k = round(reported_rad / step)
        if self._step is None:
            heading = k * step
        else:
            dt_s = max(0.0, t_s - self._t_s)
            moved = 0.5 * (self._rate_radps + rate_radps) * dt_s
            turn = round(wrap_angle((k - self._step) * step) / step)  # steps, the short way
            if turn:  # crossed into step k through its nearer edge: put on it at once
                edge = (self._step + turn - math.copysign(0.5, turn)) * step
                heading = edge + 0.5 * moved
                self._shift_anchor(heading - (self._heading + moved + self._easing))
                self._easing = 0.0
            else:
                heading = self._heading + moved
            if position is not None:
                self._easing += self._by_chord(heading + self._easing, position, way)
            eased = self._easing * min(1.0, dt_s / CHORD_EASE_S)
            heading, self._easing = heading + eased, self._easing - eased
            centre = self._step * step + turn * step
            held = min(max(heading, centre - 0.5 * step), centre + 0.5 * step)
            if held != heading:  # the report overrules the chords
                self._shift_anchor(held - (heading + self._easing))
                heading, self._easing = held, 0.0
            k = self._step + turn
        self._step, self._heading = k, heading
        self._rate_radps, self._t_s = rate_radps, t_s
        return wrap_angle(heading)

    def _shift_anchor(self, by_rad: float) -> None:
        """The estimate jumped by `by_rad`: so does the anchor's heading, which the next
        chord's turn is measured from.
        """
        if self._anchor is not None:
            x, y, heading, way = self._anchor
            self._anchor = (x, y, heading + by_rad, way)

    def _by_chord(self, heading: float, position: tuple[float, float], way: int) -> float:
        """What `heading` is off by (rad), from the direction of the chord driven since
        the last anchor if it is long enough and little turned, else 0 (the anchor moves
        on either way).
        """
        x, y = position
        anchor = self._anchor
        if way == 0 or anchor is None or anchor[3] != way:
            self._anchor = (x, y, heading, way) if way else None
            return 0.0
        ax, ay, anchor_heading, _ = anchor
        if math.hypot(x - ax, y - ay) < CHORD_M:
            return 0.0
        turned = heading - anchor_heading
        off = 0.0
        if abs(turned) <= CHORD_TURN_RAD:
            course = math.atan2(y - ay, x - ax) + (0.0 if way > 0 else math.pi)
            off = wrap_angle(course + 0.5 * turned - heading)
        self._anchor = (x, y, heading + off, way)
        return off


class SipTracker:
    """The robot's latest readings, from its SIPs, CONFIG packet and SIMSTATs.

    `heading_step_rad`: the robot reports its heading in steps this coarse (None: as
    fine as the protocol's unit), followed finer by `QuantisedHeading`.
    """

    def __init__(self, stats: ArcosStats, *, heading_step_rad: float | None = None) -> None:
        self.stats = stats
        self.factors = ConvFactors()  # set from the SYNC2 reply's subtype
        self.config: RobotConfig | None = None
        self.sip: Sip | None = None
        self.odometry: Odometry | None = None
        self.truth: TruePose | None = None  # a simulator's true pose (SIMSTAT)
        self._sim_ms, self._real_ms = 0, 0  # its updates' simulated and real times
        self._sip_clock, self._simstat_clock = CycleClock(), CycleClock()
        self._update_s = 0.0  # a simulator's last update took this long in real time
        self.heading_step_rad = heading_step_rad
        self._headings: tuple[QuantisedHeading, QuantisedHeading] | None = None
        self.sonar_m: tuple[float, ...] = (5.0,) * N_SONARS
        self.last_sip_s = time.monotonic()
        self._pose = Pose2D(0.0, 0.0, 0.0)
        self._last_xy: tuple[int, int] | None = None
        self._th0: float | None = None
        self._raw = (0.0, 0.0)  # the position in the robot's own frame, unwrapped (m)

    def new_session(self) -> None:
        """A new connection: position counters restart, the integrated pose carries on."""
        self._last_xy, self._th0 = None, None
        self._raw = (0.0, 0.0)
        self.last_sip_s = time.monotonic()
        self.lose_cycle()
        step = self.heading_step_rad
        self._headings = None if step is None else (QuantisedHeading(step), QuantisedHeading(step))

    def lose_cycle(self) -> None:
        """A frame was lost (or the link is new): the next packets start the cycle anew."""
        self._sip_clock.lose()
        self._simstat_clock.lose()

    def take(self, body: bytes, *, byte_time_s: float) -> Sip | None:
        """Account for one frame's body; the SIP if it was a good one.

        A SIP is stamped when the robot sent it: its arrival less its time on the wire
        (the whole frame at `byte_time_s` a byte), or a cycle after the last SIP if that
        is earlier (`CycleClock`); a simulator's cycle is its last update's real time.
        """
        kind = body[0]
        if kind in (SIP_STOPPED, SIP_MOVING):
            try:
                sip = decode_sip(body)
            except ProtocolError:
                self.stats.bad_sips += 1
                self.lose_cycle()
                return None
            wire_s = (len(body) + FRAME_OVERHEAD_BYTES) * byte_time_s
            self._on_sip(sip, self._sip_clock.stamp(time.monotonic() - wire_s, self._cycle_s()))
            return sip
        if kind == SIMSTAT:
            try:
                stat = decode_simstat(body)
            except ProtocolError:
                self.stats.bad_sips += 1
                self.lose_cycle()
                return None
            self._update_s = stat.last_interval_ms / 1000.0
            self._on_simstat(stat, self._simstat_clock.stamp(time.monotonic(), self._update_s))
            return None
        if kind == CONFIG_PAC:
            try:
                self.config = decode_config(body)
            except ProtocolError:
                self.stats.bad_sips += 1
        else:
            self.stats.other_frames += 1
        return None

    def _cycle_s(self) -> float:
        """The robot's cycle (s; 0 while not known): a simulator's last update, else the
        SIP cycle its CONFIG packet gives.
        """
        if self._update_s > 0.0:
            return self._update_s
        return self.config.sip_cycle_ms / 1000.0 if self.config is not None else 0.0

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
            truth=self.truth,
        )

    def _on_sip(self, sip: Sip, measured_s: float) -> None:
        f = self.factors
        w = self._yaw_rate(sip)
        v = (sip.left_vel + sip.right_vel) / 2.0 * f.vel_mmps / 1000.0
        last_xy = self._last_xy or (sip.x, sip.y)
        dx_mm = wrap_delta(sip.x, last_xy[0]) * f.dist_mm
        dy_mm = wrap_delta(sip.y, last_xy[1]) * f.dist_mm
        self._last_xy = (sip.x, sip.y)
        # (in the robot's own frame, where its heading is: positions for the chords)
        self._raw = (self._raw[0] + dx_mm / 1000.0, self._raw[1] + dy_mm / 1000.0)
        th = wrap_angle(sip.th * f.angle_rad)
        if self._headings is not None:
            th = self._headings[0].update(th, w, measured_s, position=self._raw, way=_way(v))
        if self._th0 is None:
            self._th0 = wrap_angle(th - self._pose.theta_rad)
        # ARCOS integrates x, y in its own frame; ours starts at the first SIP's pose.
        c, s = math.cos(-self._th0), math.sin(-self._th0)
        pose = Pose2D(
            self._pose.x_m + (c * dx_mm - s * dy_mm) / 1000.0,
            self._pose.y_m + (s * dx_mm + c * dy_mm) / 1000.0,
            wrap_angle(th - self._th0),
        )
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

    def _yaw_rate(self, sip: Sip) -> float:
        """rad/s: the firmware's own yaw rate if it sends one (ArRobot prefers it too),
        else from the wheel speeds.
        """
        f = self.factors
        if sip.rot_vel_x10 is not None:
            return math.radians(sip.rot_vel_x10 / 10.0)
        return (sip.right_vel - sip.left_vel) / 2.0 * f.vel_mmps * f.diff

    def _on_simstat(self, stat: SimStat, received_s: float) -> None:
        """The true pose a simulator sent (mm, whole degrees), with the latest SIP's twist.

        AMRISim truncates x and y towards zero: the middle of the millimetre they stand
        for is half a millimetre further out. It sends a SIMSTAT just before each SIP.
        """
        twist = self.odometry.twist if self.odometry is not None else Twist2D(0.0, 0.0)
        x_mm = stat.x_mm + math.copysign(0.5, stat.x_mm) if stat.x_mm else 0.0
        y_mm = stat.y_mm + math.copysign(0.5, stat.y_mm) if stat.y_mm else 0.0
        th = math.radians(stat.th_deg)
        if self._headings is not None:
            th = self._headings[1].update(
                th, twist.omega_radps, received_s, position=(x_mm / 1000.0, y_mm / 1000.0),
                way=_way(twist.v_mps),
            )  # fmt: skip
        if stat.last_interval_ms > 0:  # (its clock: simulated against real time, per update)
            self._sim_ms += stat.sim_interval_ms
            self._real_ms += stat.last_interval_ms
        name = self.config.name if self.config is not None and self.config.name else "simulator"
        self.truth = TruePose(
            Odometry(Pose2D(x_mm / 1000.0, y_mm / 1000.0, th), twist, received_s),
            source=f"{name} SIMSTAT",
            clock_rate=self._sim_ms / self._real_ms if self._real_ms else 1.0,
        )


def _way(v_mps: float) -> int:
    """+1 driving forwards, -1 backwards, 0 standing (or nearly)."""
    if abs(v_mps) < MOVING_MPS:
        return 0
    return 1 if v_mps > 0.0 else -1
