"""The `arcos` backend: a Pioneer P3DX over its ARCOS client protocol, on a serial port
(pyserial) or TCP (MobileSim convention, port 8101), both in `arcos_link`.

Connection as ARIA does it (AriaCoda `src/ArRobot.cpp`, `ArRobotConnector`): SYNC0,
SYNC1, SYNC2 (whose reply names the robot subtype, which selects the conversion
factors), OPEN, PULSE, CONFIG (the robot's own velocity limits and watchdog), ENABLE 1,
SONAR 1. A reader thread parses SIPs into odometry (15-bit position counters unwrapped),
sonar, bumpers, battery and motor state (`SipTracker`); garbage, truncated frames and
bad checksums are skipped and counted. Motion is VEL (mm/s) and RVEL (deg/s); PULSE keeps
the firmware's watchdog fed when no command is due. A link that stops delivering SIPs is
declared lost and reopened with back-off; motion must then be commanded again.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field, model_validator

from phalanx.core.config import RobotParams
from phalanx.core.errors import DriverError, DriverTimeout, DriverUnavailable, ProtocolError
from phalanx.core.geometry import Pose2D, Twist2D, wrap_angle
from phalanx.core.lifecycle import Closing
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.drivers.arcos_link import Link, open_link
from phalanx.protocols.arcos import (
    CONFIG_PAC,
    SIP_MOVING,
    SIP_STOPPED,
    SYNC0,
    SYNC1,
    SYNC2,
    Cmd,
    ConvFactors,
    FrameParser,
    RobotConfig,
    Sip,
    command,
    decode_config,
    decode_sip,
    factors_for,
    parse_sync2,
    wrap_delta,
)

log = logging.getLogger("phalanx.arcos")
N_SONARS = 16
FRAME_OVERHEAD_BYTES = 5  # FA FB, the length byte, the two checksum bytes


class ArcosSettings(BaseModel):
    """How to reach the robot. Exactly one of `port` (serial device) or `tcp` (host:port)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    port: str | None = None
    tcp: str | None = None
    baud: int = Field(default=9600, gt=0, description="9600 at power-up; 19200-115200 if set")
    connect_timeout_s: float = Field(default=5.0, gt=0.0)
    sync_retries: int = Field(default=5, ge=1)
    pulse_s: float = Field(default=0.5, gt=0.0, description="keep-alive period (ARIA: 0.5)")
    link_timeout_s: float = Field(default=1.0, gt=0.0, description="no SIP this long = lost")
    reconnect: bool = True
    reconnect_backoff_max_s: float = Field(default=2.0, gt=0.0)
    sonar: bool = True

    @model_validator(mode="after")
    def _one_link(self) -> ArcosSettings:
        if (self.port is None) == (self.tcp is None):
            raise ValueError("give exactly one of port (serial device) or tcp (host:port)")
        if self.tcp is not None:
            host, sep, port = self.tcp.rpartition(":")
            if not sep or not host or not port.isdigit():
                raise ValueError(f"tcp must be host:port, got {self.tcp!r}")
        return self

    @property
    def address(self) -> str:
        """The serial device or host:port, for messages."""
        return self.port or self.tcp or "?"


@dataclass
class ArcosStats:
    """Counters of the link."""

    sips: int = 0
    bad_sips: int = 0
    other_frames: int = 0
    reconnects: int = 0
    links_lost: int = 0
    commands_sent: int = 0


class SipTracker:
    """What the robot's packets say: SIPs into odometry, sonar, bumpers, battery and motor
    state; the CONFIG packet into the robot's own limits. No I/O, no lock: the driver
    calls it with its lock held.
    """

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

    def take(self, body: bytes, *, byte_time_s: float) -> bool:
        """Account for one frame's body; True if it was a good SIP.

        A SIP is stamped when the robot sent it: its arrival less its time on the wire
        (the whole frame at `byte_time_s` a byte).
        """
        kind = body[0]
        if kind in (SIP_STOPPED, SIP_MOVING):
            try:
                sip = decode_sip(body)
            except ProtocolError:
                self.stats.bad_sips += 1
                return False
            wire_s = (len(body) + FRAME_OVERHEAD_BYTES) * byte_time_s
            self._on_sip(sip, time.monotonic() - wire_s)
            return True
        if kind == CONFIG_PAC:
            try:
                self.config = decode_config(body)
            except ProtocolError:
                self.stats.bad_sips += 1
        else:
            self.stats.other_frames += 1
        return False

    def status(self, link_fault: str) -> RobotStatus:
        """Sonar (m), bumpers, battery and motor state of the latest SIP, and `link_fault`."""
        faults = (link_fault,) if link_fault else ()
        sip = self.sip
        if sip is None:
            return RobotStatus(faults=faults or ("no SIP yet",))
        return RobotStatus(
            sonar_ranges_m=self.sonar_m,
            bumpers=sip.bumpers,
            battery_v=sip.battery_dv / 10.0,
            motors_enabled=sip.motors_enabled and not link_fault,
            estopped=sip.estopped,
            stalled=sip.left_stall or sip.right_stall,
            faults=faults,
        )

    def _on_sip(self, sip: Sip, measured_s: float) -> None:
        f = self.factors
        now = time.monotonic()
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
        w = (sip.right_vel - sip.left_vel) / 2.0 * f.vel_mmps * f.diff
        self._pose = pose
        self.odometry = Odometry(pose, Twist2D(v, w), measured_s)
        ranges = list(self.sonar_m)
        for index, range_raw in sip.sonars:
            if 0 <= index < N_SONARS:
                ranges[index] = range_raw * f.range_mm / 1000.0
        self.sonar_m = tuple(ranges)
        self.sip = sip
        self.last_sip_s = now
        self.stats.sips += 1


class ArcosDriver(Closing):
    """A P3DX over ARCOS; implements the Driver protocol (`robot` is unused for now)."""

    name = "arcos"

    def __init__(self, settings: ArcosSettings, *, robot: RobotParams) -> None:
        self.settings = settings
        self.robot = robot
        self.stats = ArcosStats()
        self.parser = FrameParser()
        self.readings = SipTracker(self.stats)
        self.robot_name = ""
        self.subtype = ""
        self._link: Link | None = None
        self._lock = threading.RLock()  # guards the link and the readings
        self._write_lock = threading.Lock()
        self._stop = threading.Event()
        self._reader: threading.Thread | None = None
        self._closed = False
        self._last_sent_s = 0.0
        self._link_fault = ""

    # -- Driver protocol -------------------------------------------------------------

    def connect(self) -> None:
        """Open the link and run the handshake; raises DriverError if the robot is absent."""
        with self._lock:
            if self._closed:
                raise DriverError("driver closed; make a new one")
            if self._link is not None and not self._link_fault:
                self._write(command(Cmd.ENABLE, 1))  # connected already: re-enable motors
                return
            self._open_and_handshake()
        if self._reader is None:
            self._stop.clear()
            self._reader = threading.Thread(
                target=self._read_loop, name="arcos-reader", daemon=True
            )
            self._reader.start()

    def set_velocity(self, twist: Twist2D) -> None:
        """VEL (mm/s) and RVEL (deg/s). Non-finite values raise ValueError."""
        if not (math.isfinite(twist.v_mps) and math.isfinite(twist.omega_radps)):
            raise ValueError(f"non-finite velocity command {twist}")
        v_mm = round(twist.v_mps * 1000.0 / self.readings.factors.vel_mmps)
        w_deg = round(math.degrees(twist.omega_radps))
        self._send(command(Cmd.VEL, v_mm))
        self._send(command(Cmd.RVEL, w_deg))

    def read_odometry(self) -> Odometry:
        """The pose integrated from SIPs since connect (odometry frame) and the twist.

        Stamped when the robot sent the SIP: its arrival less its time on the wire (at
        9600 baud a SIP with the sonar ring takes most of a 100 ms cycle to arrive).
        """
        with self._lock:
            if self.readings.odometry is None:
                raise DriverTimeout("no SIP received yet")
            return self.readings.odometry

    def read_status(self) -> RobotStatus:
        """Sonar (m), bumpers, battery, motor and link state from the latest SIP."""
        with self._lock:
            return self.readings.status(self._link_fault)

    def stop(self) -> None:
        """STOP: decelerate to rest; motors stay enabled."""
        self._send(command(Cmd.STOP))

    def estop(self) -> None:
        """E_STOP: stop at once and disable the motors (ENABLE 1 or reconnect to resume)."""
        self._send(command(Cmd.E_STOP))

    def close(self) -> None:
        """STOP, CLOSE and release the link; safe to call twice."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._stop.set()
            if self._link is not None:
                for frame in (command(Cmd.STOP), command(Cmd.CLOSE)):
                    with contextlib.suppress(DriverError):
                        self._write(frame)
        if self._reader is not None:
            self._reader.join(2.0)
            self._reader = None
        with self._lock:
            if self._link is not None:
                self._link.close()
                self._link = None

    def __enter__(self) -> ArcosDriver:
        self.connect()
        return self

    # -- extras -----------------------------------------------------------------------

    def robot_limits(self) -> tuple[float, float] | None:
        """(v max m/s, omega max rad/s) from the robot's CONFIG packet, if it sent one."""
        config = self.readings.config
        if config is None or config.trans_vel_max_mmps <= 0:
            return None
        return config.trans_vel_max_mmps / 1000.0, math.radians(config.rot_vel_max_degps)

    @property
    def link_up(self) -> bool:
        """True while SIPs arrive."""
        with self._lock:
            return self._link is not None and not self._link_fault

    # -- link ------------------------------------------------------------------------

    def _open_and_handshake(self) -> None:
        if self._link is not None:
            self._link.close()
        s = self.settings
        self._link = open_link(port=s.port, tcp=s.tcp, baud=s.baud, timeout_s=s.connect_timeout_s)
        self.parser = FrameParser(stats=self.parser.stats)
        try:
            self._sync()
            self._write(command(Cmd.OPEN))
            self._write(command(Cmd.PULSE))
            self._write(command(Cmd.CONFIG))
            self._write(command(Cmd.ENABLE, 1))
            self._write(command(Cmd.SONAR, 1 if self.settings.sonar else 0))
            self._await_first_sip()
        except DriverError:
            self._link.close()
            self._link = None
            raise

    def _sync(self) -> None:
        for _attempt in range(self.settings.sync_retries):
            if self._try_sync():
                return
            self._write(command(Cmd.CLOSE))  # an old connection may be open: close, resync
            time.sleep(0.1)
        raise DriverTimeout(f"no ARCOS sync from {self.settings.address}")

    def _try_sync(self) -> bool:
        per_step_s = self.settings.connect_timeout_s / 3
        for step in (SYNC0, SYNC1, SYNC2):
            self._write(command(step))
            body = self._await_frame(lambda b, s=step: b[0] == s, per_step_s)
            if body is None:
                return False
            if step == SYNC2:
                self.robot_name, _type, self.subtype = parse_sync2(body)
                self.readings.factors = factors_for(self.subtype)
        return True

    def _await_frame(self, wanted: object, timeout_s: float) -> bytes | None:
        assert self._link is not None  # noqa: S101 - called with an open link
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            for body in self.parser.feed(self._link.read(min(left, 0.05))):
                if body[0] in (SIP_STOPPED, SIP_MOVING) and not wanted(body):  # type: ignore[operator]
                    return None  # SIPs during sync: an old connection is still open
                if wanted(body):  # type: ignore[operator]
                    return body
        return None

    def _await_first_sip(self) -> None:
        assert self._link is not None  # noqa: S101
        deadline = time.monotonic() + self.settings.connect_timeout_s
        self.readings.new_session()
        sips = self.stats.sips
        while time.monotonic() < deadline:
            for body in self.parser.feed(self._link.read(0.05)):
                self._dispatch(body)
            if self.stats.sips > sips:
                return
        raise DriverTimeout(f"robot at {self.settings.address} opened but sends no SIPs")

    def _write(self, data: bytes) -> None:
        link = self._link
        if link is None:
            raise DriverUnavailable("not connected")
        with self._write_lock:
            link.write(data)
            self._last_sent_s = time.monotonic()
            self.stats.commands_sent += 1

    def _send(self, data: bytes) -> None:
        with self._lock:
            if self._closed:
                raise DriverError("driver closed")
            if self._link_fault:
                raise DriverUnavailable(f"link down: {self._link_fault}")
            self._write(data)

    # -- reader ----------------------------------------------------------------------

    def _read_loop(self) -> None:
        backoff_s = 0.1
        while not self._stop.is_set():
            link = self._link
            try:
                self._read_once(link)
                backoff_s = 0.1
            except DriverError as exc:
                self._lose_link(str(exc), link)
            except Exception as exc:
                log.exception("ARCOS reader: unexpected error")
                self._lose_link(f"{type(exc).__name__}: {exc}", link)
            else:
                continue
            if not self.settings.reconnect or self._stop.wait(backoff_s):
                return
            backoff_s = min(2 * backoff_s, self.settings.reconnect_backoff_max_s)
            self._try_reconnect()

    def _read_once(self, link: Link | None) -> None:
        if link is None:
            raise DriverUnavailable("no link")
        data = link.read(0.05)
        with self._lock:
            for body in self.parser.feed(data):
                self._dispatch(body)
            now = time.monotonic()
            silent_s = now - self.readings.last_sip_s
            if silent_s > self.settings.link_timeout_s:
                raise DriverTimeout(f"no SIP for {silent_s:.2f} s")
            if now - self._last_sent_s > self.settings.pulse_s:
                self._write(command(Cmd.PULSE))

    def _lose_link(self, reason: str, link: Link | None) -> None:
        with self._lock:
            if self._closed or (link is not None and link is not self._link):
                return  # closed on purpose, or already replaced by a new link
            if not self._link_fault:
                self.stats.links_lost += 1
                log.warning("ARCOS link to %s lost: %s", self.settings.address, reason)
            self._link_fault = f"link lost: {reason}"
            if self._link is not None:
                self._link.close()
                self._link = None

    def _try_reconnect(self) -> None:
        with self._lock:
            if self._closed:
                return
            try:
                self._open_and_handshake()
            except DriverError as exc:
                self._link_fault = f"link lost: {exc}"
                return
            self.stats.reconnects += 1
            log.info("ARCOS link to %s back", self.settings.address)

    def _dispatch(self, body: bytes) -> None:
        byte_time_s = self._link.byte_time_s if self._link is not None else 0.0
        if self.readings.take(body, byte_time_s=byte_time_s):
            self._link_fault = ""  # SIPs arrive: the link is up
