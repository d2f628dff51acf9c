"""The `arcos` backend: a Pioneer P3DX over its ARCOS client protocol, on a serial port
(pyserial) or TCP (MobileSim/AMRISim convention, port 8101), both in `arcos_link`.

Connection as ARIA does it (`arcos_handshake`). A reader thread parses SIPs into odometry
(15-bit position counters unwrapped), sonar, bumpers, battery and motor state
(`arcos_tracker`); garbage, truncated frames and bad checksums are skipped and counted.
The robot's CONFIG packet gives its own speed limits (`robot_limits()`, which the safety
wrapper adopts when tighter), its watchdog (the keep-alive runs at a quarter of it at
most) and its accelerations (raised to the robot file's when lower, within the robot's
tops, so that it brakes as the agent expects). Motion is VEL (mm/s) and RVEL (deg/s);
PULSE keeps the firmware's watchdog fed when no command is due.

Faults. When no good SIP has come for `link_timeout_s` (the robot went silent, or its
SIPs arrive garbled while the link may still carry commands) the driver sends STOP at
once, reports the link lost, refuses motion and reconnects on its reader thread (trying
`fallbacks` too, and only to the same robot); the control thread is never blocked by it.
Motion must then be commanded again. E-stop: `estop()` and the robot's own E-stop
button latch in the driver (status `estopped`, motion refused) until `connect()` resets
it deliberately, whether or not the firmware latches it (AMRISim does not: it reports
no E-stop afterwards and moves on the next command).

Commands. VEL takes whole mm/s and RVEL whole deg/s: each command's rounding remainder is
carried into the next (a yaw rate of 2.4 deg/s goes out as 2, 3, 2, 2, 3, ...), so over a
few control periods the robot turns as asked, not up to half a degree a second off.

Simulators (AMRISim, MobileSim: the CONFIG packet's serial number is "SIM"). The driver
can put the robot at a true pose when it first connects (`place_at`, SIM_SET_POSE) and
asks for the robot's true pose before every SIP (SIM_STAT), reported as the status's
`truth`; their headings come in whole degrees, followed finer (`heading_step_deg`).
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time

from phalanx.core.errors import DriverError, DriverTimeout, DriverUnavailable
from phalanx.core.geometry import Twist2D
from phalanx.core.lifecycle import Closing
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.core.robot_params import RobotParams
from phalanx.drivers.arcos_handshake import Connection, HandshakeOptions, Identity, open_connection
from phalanx.drivers.arcos_link import Link
from phalanx.drivers.arcos_settings import ArcosSettings
from phalanx.drivers.arcos_tracker import ArcosStats, SipTracker
from phalanx.protocols.arcos import (
    SIMSTAT_CONTINUOUS,
    Cmd,
    FrameParser,
    RobotConfig,
    command,
    factors_for,
    sim_set_pose,
)

__all__ = ["ArcosDriver", "ArcosSettings"]
log = logging.getLogger("phalanx.arcos")
SIMULATOR_SERIAL = "SIM"  # AMRISim's and MobileSim's CONFIG packet


class ArcosDriver(Closing):
    """A P3DX over ARCOS; implements the Driver protocol."""

    name = "arcos"

    def __init__(self, settings: ArcosSettings, *, robot: RobotParams) -> None:
        self.settings = settings
        self.robot = robot
        self.stats = ArcosStats()
        self.parser = FrameParser()
        self._skipped = 0  # the parser's errors and garbage bytes at the last frame
        self.readings = SipTracker(self.stats)
        self.robot_name = ""
        self.subtype = ""
        self.address = settings.address
        self.identity: Identity | None = None  # the first robot that answered
        self._address_index = 0
        self._link: Link | None = None
        self._lock = threading.RLock()  # the link and the readings; never held over I/O waits
        self._write_lock = threading.Lock()
        self._stop = threading.Event()
        self._reader: threading.Thread | None = None
        self._closed = False
        self._last_sent_s = 0.0
        self._pulse_s = settings.pulse_s
        self._link_fault = ""
        self._estop = ""  # why the E-stop latch holds ("" when it does not)
        self._placed = False  # `place_at` done (once: a reconnect must not move the robot)
        self._remainder = (0.0, 0.0)  # what rounding left out of the last VEL and RVEL

    # -- Driver protocol -------------------------------------------------------------

    def connect(self) -> None:
        """Open the link and run the handshake; when connected already, reset the E-stop
        latch and re-enable the motors. DriverError if the robot is absent, the link is
        down (it is reconnecting), or the robot's E-stop button is still pressed.
        """
        with self._lock:
            self._check_open()
            if self._link is not None and not self._link_fault:
                self._reset_estop()
                self._write(command(Cmd.ENABLE, 1))
                return
            if self._reader is not None:
                raise DriverUnavailable(f"link to {self.address} down, reconnecting")
        connection = self._open(enable=True)
        with self._lock:
            if self._closed:
                connection.link.close()
                raise DriverError("driver closed while connecting")
            self._install(connection)
            self._stop.clear()
            self._reader = threading.Thread(target=self._read_loop, name="arcos-reader")
            self._reader.daemon = True
            self._reader.start()

    def set_velocity(self, twist: Twist2D) -> None:
        """VEL (mm/s) and RVEL (deg/s). Non-finite values raise ValueError; motion while the
        link is down or the E-stop latch holds raises DriverUnavailable (a zero command
        then sends nothing: the robot is already held at rest).
        """
        if not (math.isfinite(twist.v_mps) and math.isfinite(twist.omega_radps)):
            raise ValueError(f"non-finite velocity command {twist}")
        with self._lock:
            v_mm, w_deg, remainder = self._whole_units(twist)
            self._check_open()
            if self._link_fault or self._estop:
                if v_mm == 0 and w_deg == 0:
                    return
                if self._link_fault:
                    raise DriverUnavailable(f"link down: {self._link_fault}")
                raise DriverUnavailable(
                    f"robot E-stopped ({self._estop}): reset it deliberately (connect) first"
                )
            self._write(command(Cmd.VEL, v_mm))
            self._write(command(Cmd.RVEL, w_deg))
            self._remainder = remainder

    def _whole_units(self, twist: Twist2D) -> tuple[int, int, tuple[float, float]]:
        """(VEL mm/s, RVEL deg/s) for `twist`, each with the last command's rounding
        remainder carried in (an axis asked for 0 gets 0 and drops it), and what this
        command's rounding leaves, to carry once it is sent.
        """
        wanted = (
            twist.v_mps * 1000.0 / self.readings.factors.vel_mmps,
            math.degrees(twist.omega_radps),
        )
        out, left = [], []
        for value, carried in zip(wanted, self._remainder, strict=True):
            whole = round(value + carried) if value else 0
            out.append(whole)
            left.append(value + carried - whole if value else 0.0)
        return out[0], out[1], (left[0], left[1])

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
        """Sonar (m), bumpers, battery (V), motor and link state from the latest SIP, with
        the E-stop latch.
        """
        with self._lock:
            return self.readings.status(link_fault=self._link_fault, estop=self._estop)

    def stop(self) -> None:
        """STOP: decelerate to rest; motors stay enabled."""
        with self._lock:
            self._check_open()
            if self._link_fault:
                raise DriverUnavailable(f"link down: {self._link_fault}")
            self._write(command(Cmd.STOP))

    def estop(self) -> None:
        """E_STOP (the firmware brakes as hard as it can), latched here until `connect()`."""
        with self._lock:
            self._estop = self._estop or "e-stop (commanded)"
            if self._link is not None and not self._closed:
                with contextlib.suppress(DriverError):  # the reader notices a dead link
                    self._write(command(Cmd.E_STOP))

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

    @property
    def robot_config(self) -> RobotConfig | None:
        """The robot's CONFIG packet, if it sent one."""
        return self.readings.config

    def robot_limits(self) -> tuple[float, float] | None:
        """(v max m/s, omega max rad/s): the robot's working maxima from its CONFIG packet
        (TransVelMax, RotVelMax), None if it sent none or they are 0 (older firmware).
        """
        config = self.readings.config
        if config is None or not config.has("trans_vel_max_mmps"):
            return None
        if config.trans_vel_max_mmps <= 0 or config.rot_vel_max_degps <= 0:
            return None
        return config.trans_vel_max_mmps / 1000.0, math.radians(config.rot_vel_max_degps)

    @property
    def link_up(self) -> bool:
        """True while SIPs arrive."""
        with self._lock:
            return self._link is not None and not self._link_fault

    # -- connection ------------------------------------------------------------------

    def _handshake(self, *, enable: bool) -> HandshakeOptions:
        s = self.settings
        return HandshakeOptions(
            connect_timeout_s=s.connect_timeout_s,
            sync_retries=s.sync_retries,
            config_timeout_s=s.config_timeout_s,
            baud=s.baud,
            sonar=s.sonar,
            enable=enable,
        )

    def _open(self, *, enable: bool) -> Connection:
        """A connection to the robot: its addresses in turn, from the last one that
        worked; only the robot that answered first is accepted. Holds no lock.
        """
        addresses = self.settings.addresses
        errors: list[DriverError] = []
        for i in range(len(addresses)):
            index = (self._address_index + i) % len(addresses)
            address, tcp = addresses[index]
            try:
                connection = open_connection(
                    address,
                    self._handshake(enable=enable),
                    tcp=tcp,
                    stats=self.parser.stats,
                    abort=self._stop,
                )
            except DriverError as exc:
                errors.append(exc)
                continue
            if self.identity is not None and not self.identity.same_robot(connection.identity):
                connection.link.close()
                errors.append(
                    DriverUnavailable(f"{address}: another robot answered ({connection.identity})")
                )
                continue
            self._address_index = index
            return connection
        if len(errors) == 1:
            raise errors[0]
        raise DriverUnavailable("; ".join(str(e) for e in errors))

    def _install(self, connection: Connection) -> None:
        """Make `connection` the driver's link (lock held); DriverError if the settings
        ask to place a robot that is no simulator.
        """
        simulator = connection.identity.serial == SIMULATOR_SERIAL
        if self.settings.place_at is not None and not simulator:
            connection.link.close()
            raise DriverError(
                f"place_at is for simulated robots, but the robot at {connection.address} "
                f"is no simulator (CONFIG serial {connection.identity.serial!r}, not "
                f"{SIMULATOR_SERIAL!r}): place a real robot by hand"
            )
        if self._link is not None:
            self._link.close()
        self._link = connection.link
        self.parser = connection.parser
        self.address = connection.address
        self.identity = self.identity or connection.identity
        self.robot_name, self.subtype = connection.identity.name, connection.identity.subtype
        self.readings.factors = factors_for(self.subtype)
        self.readings.config = connection.config
        step_deg = self.settings.heading_step_deg or (1.0 if simulator else None)
        self.readings.heading_step_rad = math.radians(step_deg) if step_deg else None
        self.readings.new_session()
        self._link_fault = ""
        self._last_sent_s = time.monotonic()
        self._pulse_s = self.settings.pulse_s
        for body in connection.frames:
            self._dispatch(body)
        if connection.config is not None:
            self._adopt(connection.config)
        if self.settings.simstat if self.settings.simstat is not None else simulator:
            self._write(command(Cmd.SIM_STAT, SIMSTAT_CONTINUOUS))
        if self.settings.place_at is not None and not self._placed:
            x_m, y_m, heading_deg = self.settings.place_at
            pose = round(x_m * 1000.0), round(y_m * 1000.0), round(heading_deg)
            self._write(sim_set_pose(*pose))
            self._placed = True
            log.info("placed the robot at (%d mm, %d mm, %d deg) (SIM_SET_POSE)", *pose)

    def _adopt(self, config: RobotConfig) -> None:
        """The robot's watchdog sets the keep-alive; its (de)accelerations are raised to
        the robot file's if lower (within its tops), so STOP brakes as the agent expects.
        """
        if config.has("watchdog_ms") and config.watchdog_ms > 0:
            self._pulse_s = min(self.settings.pulse_s, config.watchdog_ms / 4000.0)
        if not self.settings.adopt_accelerations or not config.has("trans_decel_mmps2"):
            return
        r, c = self.robot, config
        trans_top, rot_top = c.trans_accel_top_mmps2, c.rot_accel_top_degps2
        wanted = (
            (Cmd.SETA, 1, c.trans_accel_mmps2, r.accel_mps2 * 1000.0, trans_top),
            (Cmd.SETA, -1, c.trans_decel_mmps2, r.decel_mps2 * 1000.0, trans_top),
            (Cmd.SETRA, 1, c.rot_accel_degps2, r.rot_accel_degps2, rot_top),
            (Cmd.SETRA, -1, c.rot_decel_degps2, r.rot_accel_degps2, rot_top),
        )
        for cmd, sign, have, want, top in wanted:
            value = round(min(want, top) if top > 0 else want)
            if 0 < have < value:
                log.info("raising the robot's %s %d to %d", cmd.name, sign * have, sign * value)
                self._write(command(cmd, sign * value))

    def _reset_estop(self) -> None:
        sip = self.readings.sip
        if sip is not None and sip.estopped:
            raise DriverError("the robot's E-stop button is still pressed: release it first")
        if self._estop:
            log.info("E-stop latch reset (was: %s)", self._estop)
        self._estop = ""

    def _check_open(self) -> None:
        if self._closed:
            raise DriverError("driver closed; make a new one")

    def _write(self, data: bytes) -> None:
        link = self._link
        if link is None:
            raise DriverUnavailable("not connected")
        with self._write_lock:
            link.write(data)
            self._last_sent_s = time.monotonic()
            self.stats.commands_sent += 1

    # -- reader ----------------------------------------------------------------------

    def _read_loop(self) -> None:
        backoff_s = 0.1
        while not self._stop.is_set():
            link = self._link
            if link is None:
                if not self.settings.reconnect or self._stop.wait(backoff_s):
                    return
                ok = self._reconnect()
                backoff_s = 0.1 if ok else min(2 * backoff_s, self.settings.reconnect_backoff_max_s)
                continue
            try:
                data = link.read(0.05)
            except DriverError as exc:
                self._lose(str(exc), link)
                continue
            except Exception as exc:
                if not self._stop.is_set():
                    log.exception("ARCOS reader: unexpected error")
                self._lose(f"{type(exc).__name__}: {exc}", link)
                continue
            self._take(data, link)

    def _take(self, data: bytes, link: Link) -> None:
        with self._lock:
            if link is not self._link:
                return
            for body in self.parser.feed(data):
                self._dispatch(body)
            now = time.monotonic()
            silent_s = now - self.readings.last_sip_s
            if silent_s > self.settings.link_timeout_s:
                self._lose(f"no SIP for {silent_s:.2f} s", link)
            elif now - self._last_sent_s > self._pulse_s:
                try:
                    self._write(command(Cmd.PULSE))
                except DriverError as exc:
                    self._lose(str(exc), link)

    def _lose(self, reason: str, link: Link) -> None:
        """SIPs stopped or the link broke: STOP first (the link may still carry commands
        though SIPs no longer arrive), then let the link go; the reader reconnects.
        """
        with self._lock:
            if self._closed or link is not self._link:
                return  # closed on purpose, or already replaced by a new link
            self.stats.links_lost += 1
            self.stats.sips_lost_s = time.monotonic()
            try:
                self._write(command(Cmd.STOP))
                self.stats.loss_stop_s = time.monotonic()
            except DriverError:
                self.stats.loss_stop_s = None
            log.warning("ARCOS link to %s lost (%s): STOP sent, reconnecting", self.address, reason)
            self._link_fault = f"link lost: {reason}"
            self._link = None
        link.close()

    def _reconnect(self) -> bool:
        with self._lock:
            if self._closed:
                return False
            enable = not self._estop
        try:
            connection = self._open(enable=enable)  # no lock held: control steps go on
        except DriverError as exc:
            with self._lock:
                self._link_fault = f"link lost: {exc}"
                self.stats.reconnect_failures += 1
            return False
        with self._lock:
            if self._closed:
                connection.link.close()
                return False
            self._install(connection)
            self.stats.reconnects += 1
        log.info("ARCOS link to %s back", connection.address)
        return True

    def _dispatch(self, body: bytes) -> None:
        byte_time_s = self._link.byte_time_s if self._link is not None else 0.0
        skipped = self.parser.stats.errors + self.parser.stats.garbage_bytes
        if skipped != self._skipped:  # a frame may have been lost before this one
            self._skipped = skipped
            self.readings.lose_cycle()
        sip = self.readings.take(body, byte_time_s=byte_time_s)
        if sip is not None and sip.estopped and not self._estop:
            self._estop = "the robot's E-stop button"
            log.warning("the robot reports its E-stop button pressed: latched")
