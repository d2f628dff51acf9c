"""A P3DX as ARCOS firmware sees it: the robot side of the protocol over a pseudo-terminal
or TCP (the MobileSim convention, port 8101), moving a simulated body.

It answers the sync/open handshake, streams standard SIPs every SIP cycle after OPEN,
obeys ENABLE, VEL, RVEL, VEL2, STOP, E_STOP, SONAR, CONFIG and CLOSE, and runs the
firmware watchdog: no client packet for `watchdog_s` stops the motors, the next packet
resumes the last setpoints (ARCOS behaviour, docs/HARDWARE.md). Faults can be
injected while it runs: garbled bytes, dropped SIPs, stalled wheels, the e-stop button,
an unplugged cable (silence both ways), a disconnect.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import select
import socket
import termios
import threading
import time
import tty
from dataclasses import dataclass, field
from typing import Protocol

from phalanx.core.config import RobotParams
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.lifecycle import Closing
from phalanx.core.localisation import OdometryErrors
from phalanx.core.motion import Body
from phalanx.protocols.arcos import (
    SYNC0,
    SYNC1,
    SYNC2,
    Cmd,
    FrameParser,
    RobotConfig,
    Sip,
    command,
    encode_config,
    encode_sip,
    factors_for,
    int_arg,
    sync2_reply,
)
from phalanx.simulator.sensors.odometry import OdometryTracker

log = logging.getLogger("phalanx.emulator")


class Link(Protocol):
    """A byte pipe to the one connected client."""

    def read(self, timeout_s: float) -> bytes | None:
        """Bytes received (b"" if none in time); None when the client is gone."""
        ...

    def write(self, data: bytes) -> None:
        """Send bytes (dropped when no client is connected)."""
        ...

    def drop_client(self) -> None:
        """Disconnect the current client (the link stays usable for the next one)."""
        ...

    def close(self) -> None:
        """Release everything."""
        ...


class PtyLink:
    """The robot's end of a pseudo-terminal; clients open `device` with pyserial."""

    def __init__(self) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        attrs = termios.tcgetattr(self._slave)
        attrs[3] &= ~termios.ECHO
        termios.tcsetattr(self._slave, termios.TCSANOW, attrs)
        self.device = os.ttyname(self._slave)
        self._closed = False

    def read(self, timeout_s: float) -> bytes | None:
        """Bytes from the client side."""
        if self._closed:
            return None
        ready, _, _ = select.select([self._master], [], [], timeout_s)
        if not ready:
            return b""
        try:
            return os.read(self._master, 4096)
        except OSError:
            return b""  # no client has the device open: nothing to read

    def write(self, data: bytes) -> None:
        """Bytes to the client side."""
        if not self._closed:
            with contextlib.suppress(OSError):
                os.write(self._master, data)

    def drop_client(self) -> None:
        """A pty cannot be unplugged without removing it: closing it is the unplug."""
        self.close()

    def close(self) -> None:
        """Close both ends (the device disappears)."""
        if not self._closed:
            self._closed = True
            for fd in (self._master, self._slave):
                with contextlib.suppress(OSError):
                    os.close(fd)


class TcpLink:
    """A listening TCP socket that serves one client at a time (MobileSim style)."""

    def __init__(self, port: int = 8101, host: str = "127.0.0.1") -> None:
        self._server = socket.create_server((host, port), reuse_port=False)
        self._server.setblocking(False)
        self.port = self._server.getsockname()[1]
        self.host = host
        self._client: socket.socket | None = None
        self._closed = False

    def read(self, timeout_s: float) -> bytes | None:
        """Accept a client if none; bytes from it."""
        if self._closed:
            return None
        sock = self._client or self._server
        ready, _, _ = select.select([sock], [], [], timeout_s)
        if not ready:
            return b""
        if self._client is None:
            with contextlib.suppress(BlockingIOError):
                self._client, _ = self._server.accept()
                self._client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            return b""
        try:
            data = self._client.recv(4096)
        except OSError:
            data = b""
        if not data:
            self.drop_client()
            return None
        return data

    def write(self, data: bytes) -> None:
        """Send to the client, if any."""
        if self._client is not None:
            try:
                self._client.sendall(data)
            except OSError:
                self.drop_client()

    def drop_client(self) -> None:
        """Close the client's connection; wait for the next one."""
        if self._client is not None:
            with contextlib.suppress(OSError):
                self._client.close()
            self._client = None

    def close(self) -> None:
        """Close the client and the listening socket."""
        if not self._closed:
            self._closed = True
            self.drop_client()
            with contextlib.suppress(OSError):
                self._server.close()


@dataclass
class EmulatorOptions:
    """Firmware settings of the emulated robot."""

    name: str = "phalanx-emu"
    subtype: str = "p3dx-sh"
    sip_cycle_s: float = 0.1
    watchdog_s: float = 2.0
    battery_v: float = 12.5
    # The odometry a SIP reports carries these wheel errors (seeded): a body moved by the
    # world already has the world's odometry, so only a stand-alone emulator sets them.
    odometry_errors: OdometryErrors | None = None
    seed: int = 0


@dataclass
class EmulatorStats:
    """What the emulator saw and did."""

    frames: int = 0
    sips_sent: int = 0
    watchdog_stops: int = 0
    commands: dict[str, int] = field(default_factory=dict)


@dataclass
class _Faults:
    garble_bytes: int = 0
    drop_sips: int = 0
    estop_button: bool = False
    unplugged: bool = False


class ArcosEmulator(Closing):
    """Runs the robot side of ARCOS on `link` in a thread, moving `body`."""

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
        self.body = body or Body(robot)
        self.factors = factors_for(self.options.subtype)
        self.stats = EmulatorStats()
        self.parser = FrameParser()
        self._odometry: OdometryTracker | None = None
        errors = self.options.odometry_errors
        if errors is not None and errors.any:
            start = self.body.state().pose
            self._odometry = OdometryTracker(
                errors, track_m=robot.track_width_m, seed=self.options.seed,
                start=(start.x_m, start.y_m, start.theta_rad),
            )  # fmt: skip
        self._faults = _Faults()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
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

    def drop_sips(self, count: int) -> None:
        """Skip the next `count` SIPs."""
        with self._lock:
            self._faults.drop_sips += count

    def stall(self, stalled: bool = True) -> None:
        """Block the wheels (the SIP reports a stall)."""
        self.body.stall(stalled)

    def press_estop(self, pressed: bool = True) -> None:
        """The red button: motors stop and stay disabled while pressed."""
        with self._lock:
            self._faults.estop_button = pressed
            if pressed:
                self._motors_enabled = False

    def unplug(self, unplugged: bool = True) -> None:
        """Cut the cable: nothing in, nothing out; the firmware watchdog does the rest."""
        with self._lock:
            self._faults.unplugged = unplugged

    def disconnect(self) -> None:
        """Unplug: drop the client (TCP) or remove the device (pty)."""
        with self._lock:
            self.link.drop_client()
            self._reset_session()

    # -- protocol --------------------------------------------------------------------

    def _reset_session(self) -> None:
        self._synced = -1  # last sync step answered
        self._open = False
        self._motors_enabled = False
        self._sonar_on = True
        self._setpoint = Twist2D(0.0, 0.0)
        self._last_packet = time.monotonic()
        self._watchdog_tripped = False
        self.body.command(Twist2D(0.0, 0.0))

    def _serve(self) -> None:
        next_sip = time.monotonic()
        last_step = time.monotonic()
        while not self._stop.is_set():
            data = self.link.read(max(0.0, min(0.02, next_sip - time.monotonic())))
            if data is None:  # the client went away: back to waiting for a sync
                with self._lock:
                    self._reset_session()
                if self._stop.wait(0.05):
                    return
                continue
            if self._faults.unplugged:
                data = b""
            for body in self.parser.feed(data):
                self._handle(body)
            now = time.monotonic()
            self._watchdog(now)
            if now >= next_sip:
                self.body.step(now - last_step)
                last_step = now
                next_sip += self.options.sip_cycle_s
                if next_sip < now:
                    next_sip = now + self.options.sip_cycle_s
                if self._open:
                    self._send_sip()

    def _count(self, name: str) -> None:
        self.stats.commands[name] = self.stats.commands.get(name, 0) + 1

    def _handle(self, body: bytes) -> None:
        self.stats.frames += 1
        cmd = body[0]
        with self._lock:
            self._last_packet = time.monotonic()
            if self._watchdog_tripped:
                self._watchdog_tripped = False
                self._apply_setpoint()  # packets are back: resume the last setpoints
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
        elif cmd == Cmd.ENABLE and arg is not None:
            self._motors_enabled = bool(arg) and not self._faults.estop_button
            self._apply_setpoint()
        elif cmd == Cmd.VEL and arg is not None:
            self._setpoint = Twist2D(
                arg * self.factors.vel_mmps / 1000.0, self._setpoint.omega_radps
            )
            self._apply_setpoint()
        elif cmd == Cmd.RVEL and arg is not None:
            self._setpoint = Twist2D(self._setpoint.v_mps, math.radians(arg))
            self._apply_setpoint()
        elif cmd == Cmd.VEL2 and arg is not None:
            raw = abs(arg) & 0xFFFF  # ARIA's com2Bytes: left in the high byte, right low
            left = _signed_byte(raw >> 8) * 20.0  # Vel2Divisor 20 mm/s
            right = _signed_byte(raw & 0xFF) * 20.0
            v = (left + right) / 2000.0
            w = (right - left) / 2.0 * self.factors.diff
            self._setpoint = Twist2D(v, w)
            self._apply_setpoint()
        elif cmd == Cmd.STOP:
            self._setpoint = Twist2D(0.0, 0.0)
            self._apply_setpoint()
        elif cmd == Cmd.E_STOP:
            self._setpoint = Twist2D(0.0, 0.0)
            self._motors_enabled = False
            self._apply_setpoint()
        elif cmd == Cmd.SONAR and arg is not None:
            self._sonar_on = bool(arg)
        elif cmd == Cmd.CONFIG:
            self._send(encode_config(self._config(), self.options.name))

    def _config(self) -> RobotConfig:
        return RobotConfig(
            robot_type="Pioneer",
            subtype=self.options.subtype,
            trans_vel_top_mmps=round(self.robot.v_max_mps * 1000),
            rot_vel_top_degps=round(self.robot.omega_max_degps),
            sip_cycle_ms=round(self.options.sip_cycle_s * 1000),
            watchdog_ms=round(self.options.watchdog_s * 1000),
            trans_vel_max_mmps=round(self.robot.v_max_mps * 1000),
            rot_vel_max_degps=round(self.robot.omega_max_degps),
        )

    def _apply_setpoint(self) -> None:
        moving = self._motors_enabled and not self._watchdog_tripped
        self.body.command(self._setpoint if moving else Twist2D(0.0, 0.0))

    def _watchdog(self, now: float) -> None:
        with self._lock:
            late = now - self._last_packet > self.options.watchdog_s
            if self._open and late and not self._watchdog_tripped:
                self._watchdog_tripped = True
                self.stats.watchdog_stops += 1
                self._apply_setpoint()
                log.warning("emulator watchdog: no packet for %.1f s, motors stopped", now)

    def _send(self, data: bytes) -> None:
        if self._faults.unplugged:
            return
        if self._faults.garble_bytes:
            n = min(self._faults.garble_bytes, len(data))
            self._faults.garble_bytes -= n
            data = bytes(b ^ 0x5A for b in data[:n]) + data[n:]
        self.link.write(data)

    def _send_sip(self) -> None:
        with self._lock:
            if self._faults.drop_sips:
                self._faults.drop_sips -= 1
                return
            self._send(encode_sip(self._sip()))
            self.stats.sips_sent += 1

    def _sip(self) -> Sip:
        state = self.body.state()
        if self._odometry is not None:  # the wheels' errors on the true motion
            state.pose = Pose2D(*self._odometry.report(*_xyt(state.pose)))
        f = self.factors
        half_track_mm = 1.0 / f.diff  # (rvel - lvel) / 2 * diff = omega
        v_mmps = state.twist.v_mps * 1000.0 / f.vel_mmps
        dv = state.twist.omega_radps * half_track_mm
        flags = 0x0001 if self._motors_enabled else 0
        flags |= 0x0002 if self._sonar_on else 0
        flags |= 0x0020 if self._faults.estop_button else 0
        sonars: tuple[tuple[int, int], ...] = ()
        if self._sonar_on:
            sonars = tuple(
                (i, round(r * 1000.0 / f.range_mm))
                for i, r in enumerate(self.body.sonar_ranges_m())
            )
        th = round(state.pose.theta_rad / f.angle_rad)
        return Sip(
            moving=abs(state.twist.v_mps) > 0 or abs(state.twist.omega_radps) > 0,
            x=round(state.pose.x_m * 1000.0 / f.dist_mm) & 0x7FFF,
            y=round(state.pose.y_m * 1000.0 / f.dist_mm) & 0x7FFF,
            th=(th + 2048) % 4096 - 2048,
            left_vel=round(v_mmps - dv),
            right_vel=round(v_mmps + dv),
            battery_dv=round(self.options.battery_v * 10),
            stall_bumpers=0x0101 if state.stalled else 0,
            flags=flags,
            sonars=sonars,
            rot_vel_x10=round(math.degrees(state.twist.omega_radps) * 10),
        )


def _xyt(pose: Pose2D) -> tuple[float, float, float]:
    return pose.x_m, pose.y_m, pose.theta_rad


def _signed_byte(value: int) -> int:
    return value - 256 if value > 127 else value
