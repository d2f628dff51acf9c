"""A P3DX as ARCOS firmware sees it: the robot side of the protocol over a pseudo-terminal
or TCP (the MobileSim convention, port 8101), moving a simulated body.

It answers the sync/open handshake, streams standard SIPs every SIP cycle after OPEN,
answers CONFIG with the whole CONFIG packet, and obeys every motion command ARIA uses
(VEL, RVEL, ROTATE, VEL2 with signed wheels, MOVE, HEAD, DHEAD, STOP, E_STOP, SETV, SETRV,
SETA, SETRA, SETO, ENABLE, SONAR, BUMPSTALL; `arcos_firmware` has the motion), each from
the moment it arrives. It runs the firmware watchdog: no client packet for `watchdog_s`
stops the motors, the next packet resumes the last setpoints (ARCOS behaviour,
docs/HARDWARE.md). Faults can be injected while it runs: garbled bytes, dropped SIPs,
stalled wheels, the e-stop button, an unplugged cable (silence both ways), a disconnect.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field

from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.lifecycle import Closing
from phalanx.core.localisation import OdometryErrors
from phalanx.core.motion import Body, BodyState
from phalanx.core.robot_params import RobotParams
from phalanx.protocols.arcos import (
    SYNC0,
    SYNC1,
    SYNC2,
    Cmd,
    ConvFactors,
    FrameParser,
    RobotConfig,
    Sip,
    command,
    encode_config,
    encode_sip,
    factors_for,
    frame,
    int_arg,
    sync2_reply,
    vel2_wheels,
)
from phalanx.simulator.arcos_firmware import FirmwareLimits, Motion
from phalanx.simulator.arcos_links import Link, PtyLink, TcpLink
from phalanx.simulator.sensors.odometry import OdometryTracker

__all__ = ["ArcosEmulator", "EmulatorOptions", "Link", "PtyLink", "TcpLink"]
log = logging.getLogger("phalanx.emulator")
STEP_S = 0.01  # the motion profile's time step while it changes
MAX_STEPS = 1000  # steps of one catch-up, at most (a 10 s gap in STEP_S steps)
# SIPs of cycles a late wake-up missed are sent at once, this many at most: longer, and
# the driver has taken the link for lost (its link timeout, 1 s by default).
MAX_LATE_SIPS = 10
VEL2_DIVISOR_MMPS = 20.0  # AriaCoda params/p3dx*.p Vel2Divisor


@dataclass
class EmulatorOptions:
    """Firmware settings of the emulated robot. E_STOP brakes at the accelerations' tops
    (AMRISim at once; 1000 mm/s² is what ARIA assumes of a robot without CONFIG).
    """

    name: str = "phalanx-emu"
    subtype: str = "p3dx-sh"
    serial: str = "PHALANX-EMU"
    sip_cycle_s: float = 0.1
    watchdog_s: float = 2.0
    battery_v: float = 12.5
    low_battery_v: float = 11.0
    trans_accel_top_mmps2: float = 1000.0
    rot_accel_top_degps2: float = 300.0
    # The odometry a SIP reports carries these wheel errors (seeded): a body moved by the
    # world already has the world's odometry, so only a stand-alone emulator sets them.
    odometry_errors: OdometryErrors | None = None
    seed: int = 0


@dataclass
class EmulatorStats:
    """What the emulator saw and did; `received`: the latest commands (monotonic time of
    arrival, name), oldest first.
    """

    frames: int = 0
    sips_sent: int = 0
    watchdog_stops: int = 0
    commands: dict[str, int] = field(default_factory=dict)
    received: deque[tuple[float, str]] = field(default_factory=lambda: deque(maxlen=1000))

    def first_after(self, name: str, since_s: float) -> float | None:
        """When command `name` first arrived at or after `since_s` (None: not since)."""
        return next((t for t, n in list(self.received) if n == name and t >= since_s), None)


@dataclass
class _Faults:
    garble_bytes: int = 0
    garble_until_s: float = 0.0
    drop_sips: int = 0
    estop_button: bool = False
    unplugged: bool = False


class ArcosEmulator(Closing):
    """Runs the robot side of ARCOS on `link` in a thread, moving `body`.

    Without a `body` it moves its own, able to brake at the firmware's tops (an E_STOP);
    a body given (e.g. one the world moves) keeps its own limits.
    """

    def __init__(
        self,
        link: Link,
        robot: RobotParams,
        options: EmulatorOptions | None = None,
        body: Body | None = None,
    ) -> None:
        self.link = link
        self.robot = robot
        self.options = options or EmulatorOptions()
        self.factors = factors_for(self.options.subtype)
        o = self.options
        self.rated = FirmwareLimits.of(
            robot, trans_accel_top=o.trans_accel_top_mmps2, rot_accel_top=o.rot_accel_top_degps2
        )
        self.body = body or Body(self.rated.body_params(robot))
        self.stats = EmulatorStats()
        self.parser = FrameParser()
        self._odometry: OdometryTracker | None = None
        errors = o.odometry_errors
        if errors is not None and errors.any:
            start = self.body.state().pose
            self._odometry = OdometryTracker(
                errors, track_m=robot.track_width_m, seed=o.seed,
                start=(start.x_m, start.y_m, start.theta_rad),
            )  # fmt: skip
        self._faults = _Faults()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._stepped_s = time.monotonic()
        self._reset_session()

    # -- lifecycle -------------------------------------------------------------------

    def start(self) -> ArcosEmulator:
        """Serve in a background thread."""
        self._thread = threading.Thread(target=self._serve, name="arcos-emulator", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop serving and release the link (safe twice)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        self.link.close()

    def __enter__(self) -> ArcosEmulator:
        return self.start()

    # -- fault injection -------------------------------------------------------------

    def garble(self, n_bytes: int = 16) -> None:
        """Corrupt the next `n_bytes` bytes sent (checksums will fail)."""
        with self._lock:
            self._faults.garble_bytes += n_bytes

    def garble_for(self, seconds: float) -> None:
        """Corrupt every byte sent for the next `seconds` (a noisy line)."""
        with self._lock:
            self._faults.garble_until_s = time.monotonic() + seconds

    def drop_sips(self, count: int) -> None:
        """Skip the next `count` SIPs."""
        with self._lock:
            self._faults.drop_sips += count

    def stall(self, stalled: bool = True) -> None:
        """Block the wheels (the SIP reports a stall)."""
        self.body.stall(stalled)

    def press_estop(self, pressed: bool = True) -> None:
        """The red button: the motors brake at once and stay disabled while it is pressed
        (and after: released, they wait for ENABLE 1).
        """
        with self._lock:
            self._faults.estop_button = pressed
            if pressed:
                self._motors_enabled = False
                self.motion.estop()

    def unplug(self, unplugged: bool = True) -> None:
        """Cut the cable: nothing in, nothing out; the firmware watchdog does the rest."""
        with self._lock:
            self._faults.unplugged = unplugged

    def disconnect(self) -> None:
        """Unplug: drop the client (TCP) or remove the device (pty)."""
        with self._lock:
            self.link.drop_client()
            self._reset_session()

    # -- what the firmware is doing --------------------------------------------------

    @property
    def target(self) -> Twist2D:
        """The speeds the firmware is bringing the wheels to (m/s, rad/s): what it was last
        told, within its limits; zero after STOP, E_STOP or its watchdog.
        """
        with self._lock:
            return self.motion.target

    def config(self) -> RobotConfig:
        """The CONFIG packet it sends now (working values as SETV & co. left them)."""
        return _config_of(self.options, self.rated, self.motion.limits)

    @property
    def limits(self) -> FirmwareLimits:
        """The working maxima and (de)accelerations now (SETV, SETA, ... change them)."""
        with self._lock:
            return self.motion.limits

    # -- protocol --------------------------------------------------------------------

    def _reset_session(self) -> None:
        self._synced = -1  # last sync step answered
        self._open = False
        self._motors_enabled = False
        self._sonar_on = True
        self._bumpstall = 0
        self._last_packet = time.monotonic()
        self._watchdog_tripped = False
        self._odom_origin = getattr(self, "_odom_origin", Pose2D(0.0, 0.0, 0.0))
        # A new connection starts from the FLASH defaults (operations manual: SETV & co.
        # revert when the client disconnects).
        # The wheels keep turning as they were and come to rest at the FLASH deceleration.
        moving = getattr(self, "motion", None)
        self.motion = Motion(
            self.rated, diff_conv=self.factors.diff, vel2_divisor=VEL2_DIVISOR_MMPS
        )
        if moving is not None:
            self.motion.v_mmps, self.motion.w_degps = moving.v_mmps, moving.w_degps

    def _serve(self) -> None:
        next_sip = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            wait_s = next_sip - now
            if self.motion.busy:
                wait_s = min(wait_s, STEP_S)
            data = self.link.read(max(0.0, wait_s))
            if data is None:  # the client went away: back to waiting for a sync
                with self._lock:
                    self._reset_session()
                if self._stop.wait(0.05):
                    return
                continue
            if self._faults.unplugged:
                data = b""
            now = time.monotonic()
            next_sip = self._send_due_sips(next_sip, now)
            self._advance(now)  # commands act from the moment they arrive
            for body in self.parser.feed(data):
                self._handle(body)
            self._watchdog(time.monotonic())

    def _send_due_sips(self, next_sip: float, now: float) -> float:
        """Send the SIP of each cycle due by `now`, describing the robot at that cycle's
        time, as firmware on its own clock does: a wake-up late on a loaded machine sends
        the cycles it missed at once (at most MAX_LATE_SIPS; past that the cycle starts
        again now), each as it was, not the robot as it is when the SIPs go out. Returns
        the time of the next cycle.
        """
        cycle_s = self.options.sip_cycle_s
        if now - next_sip > MAX_LATE_SIPS * cycle_s:
            next_sip = now
        while next_sip <= now:
            self._advance(next_sip)
            if self._open:
                self._send_sip(next_sip)
            next_sip += cycle_s
        return next_sip

    def _advance(self, now: float) -> None:
        """Run the motion profile and the body from the last step to `now`, `STEP_S` at a
        time as a firmware's own cycle runs (at most `MAX_STEPS` of them, longer ones past
        that): a wake-up of this process that comes late on a loaded machine must not
        make one long step of a turn to a heading or of a move, which overshoots it.
        """
        with self._lock:
            dt_s = now - self._stepped_s
            self._stepped_s = max(self._stepped_s, now)
        step_s = max(STEP_S, dt_s / MAX_STEPS)
        while dt_s > 0.0:
            this_s = min(step_s, dt_s)
            dt_s -= this_s
            with self._lock:
                pose = self._odom_origin.relative(self.body.state().pose)
                twist = self.motion.step(this_s, pose)
                self.body.command(twist if self._motors_enabled else Twist2D(0.0, 0.0))
            self.body.step(this_s)

    def _count(self, name: str) -> None:
        self.stats.commands[name] = self.stats.commands.get(name, 0) + 1
        self.stats.received.append((time.monotonic(), name))

    def _handle(self, body: bytes) -> None:
        self.stats.frames += 1
        cmd = body[0]
        with self._lock:
            self._last_packet = time.monotonic()
            if self._watchdog_tripped:
                self._watchdog_tripped = False
                self.motion.held = False  # packets are back: resume the last setpoints
            if not self._open:
                self._handle_sync(cmd)
                return
            self._handle_command(cmd, body)

    def _handle_sync(self, cmd: int) -> None:
        # OPEN shares its number with SYNC1 (and PULSE with SYNC0): after SYNC2, 1 opens.
        if cmd == Cmd.OPEN and self._synced >= 2:
            self._open = True
            self._count("OPEN")
        elif cmd == SYNC0:
            self._synced = 0
            self._send(command(SYNC0))
        elif cmd == SYNC1 and self._synced >= 0:
            self._synced = 1
            self._send(command(SYNC1))
        elif cmd == SYNC2 and self._synced >= 1:
            self._synced = 2
            self._send(sync2_reply(self.options.name, "Pioneer", self.options.subtype))

    def _handle_command(self, cmd: int, body: bytes) -> None:
        arg = int_arg(body)
        try:
            name = Cmd(cmd).name
        except ValueError:
            name = f"unknown-{cmd}"
        self._count(name)
        if cmd == Cmd.CLOSE:
            self._reset_session()
        elif cmd == Cmd.CONFIG:
            self._send(frame(encode_config(self.config())))
        elif cmd == Cmd.STOP:
            self.motion.stop()
        elif cmd == Cmd.E_STOP:
            self.motion.estop()
        elif cmd == Cmd.SETO:  # the odometry frame starts here
            self._odom_origin = self.body.state().pose
        elif arg is not None:
            self._with_argument(cmd, arg)

    def _with_argument(self, cmd: int, arg: int) -> None:
        m = self.motion
        pose = self._odom_origin.relative(self.body.state().pose)
        moving = self._motors_enabled  # a disabled robot ignores motion commands
        if cmd == Cmd.ENABLE:
            self._motors_enabled = bool(arg) and not self._faults.estop_button
            if not self._motors_enabled:
                m.stop()
        elif cmd == Cmd.VEL and moving:
            m.vel(arg * self.factors.vel_mmps)
        elif cmd in (Cmd.RVEL, Cmd.ROTATE) and moving:
            m.rvel(arg)
        elif cmd == Cmd.VEL2 and moving:
            m.vel2(*vel2_wheels(arg))
        elif cmd == Cmd.MOVE and moving:
            m.move(arg, pose)  # mm, as AMRISim and ARIA take it
        elif cmd == Cmd.HEAD and moving:
            m.head(arg)
        elif cmd == Cmd.DHEAD and moving:
            m.dhead(arg, pose)
        elif cmd in (Cmd.SETV, Cmd.SETRV):
            m.set_limit("trans_vel_max" if cmd == Cmd.SETV else "rot_vel_max", arg)
        elif cmd in (Cmd.SETA, Cmd.SETRA):
            kind = "trans" if cmd == Cmd.SETA else "rot"
            m.set_limit(f"{kind}_{'accel' if arg >= 0 else 'decel'}", abs(arg))
        elif cmd == Cmd.SONAR:
            self._sonar_on = bool(arg)
        elif cmd == Cmd.BUMPSTALL:
            self._bumpstall = arg if 0 <= arg <= 3 else self._bumpstall

    def _watchdog(self, now: float) -> None:
        with self._lock:
            silent_s = now - self._last_packet
            if self._open and silent_s > self.options.watchdog_s and not self._watchdog_tripped:
                self._watchdog_tripped = True
                self.motion.held = True
                self.stats.watchdog_stops += 1
                log.warning("emulator watchdog: no packet for %.1f s, motors stopped", silent_s)

    def _send(self, data: bytes) -> None:
        if self._faults.unplugged:
            return
        if time.monotonic() < self._faults.garble_until_s:
            data = bytes(b ^ 0x5A for b in data)
        elif self._faults.garble_bytes:
            n = min(self._faults.garble_bytes, len(data))
            self._faults.garble_bytes -= n
            data = bytes(b ^ 0x5A for b in data[:n]) + data[n:]
        self.link.write(data)

    def _send_sip(self, at_s: float) -> None:
        """The SIP of the cycle at `at_s` (monotonic; the body is stepped to it)."""
        with self._lock:
            if self._faults.drop_sips:
                self._faults.drop_sips -= 1
                return
            flags = 0x0001 if self._motors_enabled else 0
            flags |= 0x001E if self._sonar_on else 0  # bits 1-4: the sonar arrays
            flags |= 0x0020 if self._faults.estop_button else 0
            state = self.body.state_at(at_s)
            sonars = self.body.sonar_ranges_m() if self._sonar_on else None
            pose = self._odom_origin.relative(_measured(self._odometry, state.pose))
            sip = _sip_of(
                state, pose, self.factors, flags=flags, sonars=sonars,
                battery_v=self.options.battery_v,
            )  # fmt: skip
            self._send(encode_sip(sip))
            self.stats.sips_sent += 1


def _config_of(o: EmulatorOptions, rated: FirmwareLimits, lim: FirmwareLimits) -> RobotConfig:
    """The CONFIG packet of a robot with options `o`, tops `rated`, working values `lim`."""
    return RobotConfig(
        robot_type="Pioneer",
        subtype=o.subtype,
        serial=o.serial,
        rot_vel_top_degps=round(rated.rot_vel_top),
        trans_vel_top_mmps=round(rated.trans_vel_top),
        rot_accel_top_degps2=round(rated.rot_accel_top),
        trans_accel_top_mmps2=round(rated.trans_accel_top),
        name=o.name,
        sip_cycle_ms=round(o.sip_cycle_s * 1000),
        front_sonar=1,
        rear_sonar=1,
        low_battery_dv=round(o.low_battery_v * 10),
        watchdog_ms=round(o.watchdog_s * 1000),
        rot_vel_max_degps=round(lim.rot_vel_max),
        trans_vel_max_mmps=round(lim.trans_vel_max),
        rot_accel_degps2=round(lim.rot_accel),
        rot_decel_degps2=round(lim.rot_decel),
        trans_accel_mmps2=round(lim.trans_accel),
        trans_decel_mmps2=round(lim.trans_decel),
        firmware_version="phalanx-1.0",
    )


def _sip_of(
    state: BodyState,
    pose: Pose2D,
    f: ConvFactors,
    *,
    flags: int,
    sonars: tuple[float, ...] | None,
    battery_v: float,
) -> Sip:
    """The SIP of a body in `state` at odometry `pose` (`sonars`: ranges in m, None: off)."""
    half_track_mm = 1.0 / f.diff  # (rvel - lvel) / 2 * diff = omega
    v_mmps = state.twist.v_mps * 1000.0 / f.vel_mmps
    dv = state.twist.omega_radps * half_track_mm
    readings: tuple[tuple[int, int], ...] = ()
    if sonars is not None:
        readings = tuple((i, round(r * 1000.0 / f.range_mm)) for i, r in enumerate(sonars))
    th = round(pose.theta_rad / f.angle_rad)
    return Sip(
        moving=abs(state.twist.v_mps) > 0 or abs(state.twist.omega_radps) > 0,
        x=round(pose.x_m * 1000.0 / f.dist_mm) & 0x7FFF,
        y=round(pose.y_m * 1000.0 / f.dist_mm) & 0x7FFF,
        th=(th + 2048) % 4096 - 2048,
        left_vel=round(v_mmps - dv),
        right_vel=round(v_mmps + dv),
        battery_dv=round(battery_v * 10),
        stall_bumpers=0x0101 if state.stalled else 0,
        flags=flags,
        sonars=readings,
        rot_vel_x10=round(math.degrees(state.twist.omega_radps) * 10),
        fault_flags=0,
    )


def _measured(odometry: OdometryTracker | None, pose: Pose2D) -> Pose2D:
    """The pose the wheels measure when the body is at `pose` (with the odometry error
    model, which advances at each SIP; exact without it).
    """
    if odometry is None:
        return pose
    return Pose2D(*odometry.report(pose.x_m, pose.y_m, pose.theta_rad))
