"""The `canopen` backend: a differential drive of two CiA 402 drives in profile velocity
mode over python-can, with the `canopen` library doing SDO, PDO, NMT and EMCY.

Connect: wait for each drive's heartbeat, PRE-OPERATIONAL, profile velocity mode (3) and
its ramps by SDO, the 402 state machine walked to OPERATION ENABLED by controlword
(fault reset first if needed), PDOs from the object dictionary, NMT start. Run: target
velocities by RPDO1 (controlword + target), statusword and actual velocity by TPDO1,
odometry integrated from the measured wheel speeds. Supervision: a drive whose heartbeat
is missing for `heartbeat_timeout_s`, or which reports an EMCY or FAULT, stops the robot
(zero targets and quick stop on both wheels) and the fault is reported until `connect()`
resets it; so does a running drive whose heartbeat says it left OPERATIONAL (it rebooted,
or was stopped), and one that reports a wheel speed no drive of this robot could reach
(over `IMPLAUSIBLE_FACTOR` times the wheel speed limit: a corrupt or forged frame, never
integrated into the odometry). The wheel geometry and speed limit are the robot
parameter file's.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Literal

import canopen
from pydantic import BaseModel, ConfigDict, Field

from phalanx.core.errors import DriverError, DriverTimeout, DriverUnavailable
from phalanx.core.geometry import Pose2D, Twist2D, integrate_unicycle
from phalanx.core.lifecycle import Closing
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.core.robot_params import RobotParams
from phalanx.protocols.cia402 import Cw, drive_od

log = logging.getLogger("phalanx.canopen")
STATE_MASK = 0x6F
OPERATION_ENABLED = 0x27
QUICK_STOP_ACTIVE = 0x07
SWITCH_ON_DISABLED_MASK, SWITCH_ON_DISABLED = 0x4F, 0x40
FAULT_MASK, FAULT = 0x4F, 0x08
PROFILE_VELOCITY = 3
NMT_OPERATIONAL = 5
IMPLAUSIBLE_FACTOR = 2.0
MAX_FAULTS = 16  # reasons kept; more (an EMCY flood) are counted in `faults_dropped`
SDO_RETRY_S = 0.05  # pause before the enabling sequence runs again after a garbled answer
# An SDO transfer met by a garbled answer: no answer, or one too short to read (canopen's
# SDO client unpacks the response's command byte without checking that there is one, and
# raises `struct.error` on an empty frame with the server's COB-ID).
GARBLED_SDO: tuple[type[Exception], ...] = (canopen.SdoCommunicationError, struct.error)


class CanopenSettings(BaseModel):
    """Bus, node ids and the drives' velocity scale (the wheels are the robot file's)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int = Field(default=500_000, gt=0, le=8_000_000)  # (CAN FD's fastest data phase)
    left_node_id: int = Field(default=1, ge=1, le=127)
    right_node_id: int = Field(default=2, ge=1, le=127)
    # (at most: the fastest wheel's counts stay well inside the target velocity's int32)
    counts_per_radps: float = Field(
        default=1000.0, gt=0.0, le=1e6, description="drive units per rad/s"
    )
    left_sign: Literal[-1, 1] = Field(default=1, description="+1 or -1: mounting direction")
    right_sign: Literal[-1, 1] = Field(default=-1, description="mirrored on the right side")
    heartbeat_timeout_s: float = Field(default=0.3, gt=0.0, le=10.0)
    connect_timeout_s: float = Field(default=3.0, gt=0.0, le=3600.0)
    accel_counts_ps2: int = Field(default=10_000, gt=0, le=2**32 - 1)  # (UNSIGNED32, 0x6083)


@dataclass(frozen=True)
class WheelGeometry:
    """The differential drive's wheels, from the robot parameter file."""

    radius_m: float
    track_width_m: float
    max_radps: float  # the wheel speed limit

    @classmethod
    def of(cls, robot: RobotParams) -> WheelGeometry:
        """`robot`'s wheels; the limit is its wheel rim speed over the wheel radius."""
        return cls(
            radius_m=robot.wheel_radius_m,
            track_width_m=robot.track_width_m,
            max_radps=robot.wheel_v_max_mps / robot.wheel_radius_m,
        )


@dataclass
class _Wheel:
    name: str
    node: canopen.RemoteNode
    sign: int
    last_beat_s: float = 0.0
    statusword: int = 0
    speed_radps: float = 0.0
    tpdos: int = 0
    pdo_ready: bool = False


@dataclass
class CanopenStats:
    """Counters of the bus."""

    tpdos: int = 0
    rpdos: int = 0
    emcys: int = 0
    heartbeat_losses: int = 0
    faults: list[str] = field(default_factory=list)
    faults_dropped: int = 0


class CanopenDriver(Closing):
    """Two CiA 402 drives as one differential-drive robot; implements the Driver protocol."""

    name = "canopen"

    def __init__(self, settings: CanopenSettings, *, robot: RobotParams) -> None:
        self.settings = settings
        self.geometry = WheelGeometry.of(robot)
        self.stats = CanopenStats()
        self._lock = threading.RLock()  # readings, faults, PDO sends; never held while waiting
        self._connect_lock = threading.Lock()
        self._network: canopen.Network | None = None
        self._wheels: tuple[_Wheel, _Wheel] | None = None
        self._faults: list[str] = []
        # An E-stop, latched until connect(): ours (`estop()`), or a drive that quick-stopped
        # without being told to (its emergency-stop input); `_quick_stopping`: we told it.
        self._estop = ""
        self._quick_stopping = False
        self._running = False  # both drives enabled by connect(), not stopped since
        self._pose = Pose2D(0.0, 0.0, 0.0)
        self._twist = Twist2D(0.0, 0.0)
        self._odom_s = time.monotonic()
        self._stop = threading.Event()
        self._supervisor: threading.Thread | None = None
        self._closed = False

    # -- Driver protocol -------------------------------------------------------------

    def connect(self) -> None:
        """Open the bus (once) and bring both drives to OPERATION ENABLED."""
        # Bus waits happen without `_lock`: the bus thread's callbacks take it, and a
        # blocked callback would hold back the heartbeats being waited for.
        with self._connect_lock:
            if self._closed:
                raise DriverError("driver closed; make a new one")
            if self._network is None:
                self._open_bus()
            assert self._wheels is not None  # noqa: S101 - set by _open_bus
            for wheel in self._wheels:
                self._enable(wheel)
            with self._lock:
                self._faults.clear()
                self._estop, self._quick_stopping = "", False
                self._running = True
                self._odom_s = time.monotonic()
        if self._supervisor is None:
            self._supervisor = threading.Thread(target=self._supervise, name="can-supervisor")
            self._supervisor.daemon = True
            self._supervisor.start()

    def set_velocity(self, twist: Twist2D) -> None:
        """Wheel targets from (v, omega) by RPDO1. Refused while a drive is faulted."""
        if not (math.isfinite(twist.v_mps) and math.isfinite(twist.omega_radps)):
            raise ValueError(f"non-finite velocity command {twist}")
        with self._lock:
            self._check_usable()
            if self._faults or self._estop:
                reasons = [*self._faults, *([self._estop] if self._estop else [])]
                raise DriverUnavailable(f"drives stopped: {'; '.join(reasons)}")
            g = self.geometry
            half = twist.omega_radps * g.track_width_m / 2.0
            left = (twist.v_mps - half) / g.radius_m
            right = (twist.v_mps + half) / g.radius_m
            scale = max(1.0, abs(left) / g.max_radps, abs(right) / g.max_radps)
            assert self._wheels is not None  # noqa: S101
            for wheel, radps in zip(self._wheels, (left / scale, right / scale), strict=True):
                self._send(wheel, Cw.ENABLE_OPERATION, radps)

    def read_odometry(self) -> Odometry:
        """Pose integrated from the drives' measured wheel speeds since connect."""
        with self._lock:
            if self._wheels is None:
                raise DriverTimeout("not connected")
            return Odometry(self._pose, self._twist, self._odom_s)

    def read_status(self) -> RobotStatus:
        """Motor state of both drives and any fault; no sonar or bumpers on this robot."""
        with self._lock:
            wheels = self._wheels or ()
            enabled = bool(wheels) and all(
                w.statusword & STATE_MASK == OPERATION_ENABLED for w in wheels
            )
            return RobotStatus(
                motors_enabled=enabled and not self._faults and not self._estop,
                estopped=bool(self._estop),
                stalled=False,
                faults=tuple(self._faults),
            )

    def stop(self) -> None:
        """Zero targets, drives stay enabled."""
        with self._lock:
            if self._wheels is None or self._closed:
                return
            for wheel in self._wheels:
                self._send(wheel, Cw.ENABLE_OPERATION, 0.0)

    def estop(self) -> None:
        """Quick stop on both drives (they ramp down and disable), reported as an E-stop
        until `connect()` re-enables them.
        """
        with self._lock:
            if self._wheels is None:
                return
            self._quick_stop_all()
            self._estop = self._estop or "e-stop (commanded)"

    def close(self) -> None:
        """Zero targets, shut the drives down (disabled), leave the bus; safe twice."""
        with self._lock:
            if self._closed:
                return
            self._closed, self._running = True, False
            self._stop.set()
            if self._wheels is not None:
                for wheel in self._wheels:
                    try:
                        self._send(wheel, Cw.SHUTDOWN, 0.0)
                    except Exception as exc:
                        log.warning("shutdown of %s failed: %s", wheel.name, exc)
        if self._supervisor is not None:
            self._supervisor.join(2.0)
            self._supervisor = None
        with self._lock:
            network, self._network = self._network, None
        if network is not None:
            network.disconnect()  # joins the bus thread: never with `_lock` held

    def __enter__(self) -> CanopenDriver:
        self.connect()
        return self

    # -- bus -------------------------------------------------------------------------

    def _check_usable(self) -> None:
        if self._closed:
            raise DriverError("driver closed")
        if self._wheels is None:
            raise DriverUnavailable("not connected")

    def _open_bus(self) -> None:
        s = self.settings
        network = canopen.Network()
        try:
            if s.interface == "virtual":
                network.connect(interface=s.interface, channel=s.channel)
            else:
                network.connect(interface=s.interface, channel=s.channel, bitrate=s.bitrate)
        except Exception as exc:
            raise DriverUnavailable(f"cannot open CAN {s.interface}:{s.channel}: {exc}") from exc
        wheels = []
        for name, node_id, sign in (
            ("left", s.left_node_id, s.left_sign),
            ("right", s.right_node_id, s.right_sign),
        ):
            node = network.add_node(node_id, drive_od(node_id))
            wheel = _Wheel(name, node, sign)
            node.nmt.add_heartbeat_callback(lambda state, w=wheel: self._on_beat(w, state))
            node.emcy.add_callback(lambda err, w=wheel: self._on_emcy(w, err))
            wheels.append(wheel)
        self._network = network
        self._wheels = (wheels[0], wheels[1])

    def _enable(self, wheel: _Wheel) -> None:
        # An SDO answer nobody asked for (a corrupt or forged frame, left on the bus) is
        # taken for the next transfer's: the sequence runs again until the bus is clean,
        # for up to `connect_timeout_s` (a burst a slow bus thread still works through
        # outlasts any fixed number of attempts).
        deadline = time.monotonic() + self.settings.connect_timeout_s
        while True:
            try:
                self._enable_once(wheel)
                return
            except DriverUnavailable as exc:
                if not isinstance(exc.__cause__, GARBLED_SDO):
                    raise
                if time.monotonic() + SDO_RETRY_S > deadline:
                    raise
                log.warning("%s drive: %s; again", wheel.name, exc)
                time.sleep(SDO_RETRY_S)

    def _enable_once(self, wheel: _Wheel) -> None:
        s, node = self.settings, wheel.node
        try:
            node.nmt.wait_for_heartbeat(s.connect_timeout_s)
            _clean_slate(node)
            node.nmt.state = "PRE-OPERATIONAL"
            node.sdo[0x6060].raw = PROFILE_VELOCITY
            node.sdo[0x6083].raw = s.accel_counts_ps2
            node.sdo[0x6084].raw = s.accel_counts_ps2
            if node.sdo[0x6041].raw & FAULT_MASK == FAULT:
                node.sdo[0x6040].raw = 0x00
                node.sdo[0x6040].raw = Cw.FAULT_RESET  # rising edge of bit 7
            for command, expected in (
                (Cw.SHUTDOWN, 0x21),
                (Cw.SWITCH_ON, 0x23),
                (Cw.ENABLE_OPERATION, OPERATION_ENABLED),
            ):
                node.sdo[0x60FF].raw = 0
                node.sdo[0x6040].raw = command
                self._await_state(wheel, expected)
            if not wheel.pdo_ready:
                node.tpdo.read(from_od=True)
                node.rpdo.read(from_od=True)
                node.tpdo[1].add_callback(lambda pdo, w=wheel: self._on_tpdo(w, pdo))
                wheel.pdo_ready = True
            node.nmt.state = "OPERATIONAL"
            # PDOs count only once the drive is OPERATIONAL: wait for its heartbeat to say so.
            deadline = time.monotonic() + s.connect_timeout_s
            while node.nmt.wait_for_heartbeat(s.connect_timeout_s) != "OPERATIONAL":
                if time.monotonic() > deadline:
                    raise DriverTimeout(f"{wheel.name} drive did not become OPERATIONAL")
        except (canopen.SdoAbortedError, canopen.nmt.NmtError, *GARBLED_SDO) as exc:
            raise DriverUnavailable(f"{wheel.name} drive (node {node.id}): {exc}") from exc
        wheel.last_beat_s = time.monotonic()

    def _await_state(self, wheel: _Wheel, expected: int) -> None:
        deadline = time.monotonic() + self.settings.connect_timeout_s
        while (status := int(wheel.node.sdo[0x6041].raw)) & STATE_MASK != expected:
            if time.monotonic() > deadline:
                raise DriverTimeout(
                    f"{wheel.name} drive stuck at statusword {status:#06x}, wanted {expected:#x}"
                )
            time.sleep(0.01)
        wheel.statusword = status

    def _send(self, wheel: _Wheel, controlword: int, radps: float) -> None:
        counts = round(wheel.sign * radps * self.settings.counts_per_radps)
        rpdo = wheel.node.rpdo[1]
        rpdo["Controlword"].raw = int(controlword)
        rpdo["Target velocity"].raw = counts
        rpdo.transmit()
        self.stats.rpdos += 1

    # -- callbacks (bus thread) and supervision --------------------------------------

    def _on_beat(self, wheel: _Wheel, state: int) -> None:
        wheel.last_beat_s = time.monotonic()
        if state != NMT_OPERATIONAL and self._running:
            with self._lock:
                self._fault(f"{wheel.name} drive left OPERATIONAL (NMT state {state:#x})")

    def _on_emcy(self, wheel: _Wheel, error: canopen.emcy.EmcyError) -> None:
        if error.code == 0:
            return  # "error reset / no error"
        with self._lock:
            self.stats.emcys += 1
            self._fault(f"{wheel.name} drive EMCY {error.code:#06x} ({error.get_desc()})")

    def _on_tpdo(self, wheel: _Wheel, pdo: canopen.pdo.PdoMap) -> None:
        with self._lock:
            wheel.statusword = int(pdo["Statusword"].raw)
            counts = int(pdo["Velocity actual value"].raw)
            speed_radps = wheel.sign * counts / self.settings.counts_per_radps
            if abs(speed_radps) > IMPLAUSIBLE_FACTOR * self.geometry.max_radps:
                self._fault(f"{wheel.name} drive reports an implausible {speed_radps:.0f} rad/s")
                return
            wheel.speed_radps = speed_radps
            wheel.tpdos += 1
            self.stats.tpdos += 1
            if wheel.statusword & FAULT_MASK == FAULT:
                self._fault(f"{wheel.name} drive in FAULT")
            if self._running and not self._quick_stopping and _stopped_itself(wheel.statusword):
                # Nobody here asked for it: the drive's own emergency-stop input.
                log.error("%s drive stopped on its own (statusword %#06x): e-stop",
                          wheel.name, wheel.statusword)  # fmt: skip
                self._estop = f"{wheel.name} drive e-stop input"
                self._quick_stop_all()
            self._integrate()

    def _integrate(self) -> None:
        assert self._wheels is not None  # noqa: S101
        now = time.monotonic()
        left, right = self._wheels
        g = self.geometry
        v = g.radius_m * (left.speed_radps + right.speed_radps) / 2.0
        w = g.radius_m * (right.speed_radps - left.speed_radps) / g.track_width_m
        self._pose = integrate_unicycle(self._pose, self._twist, now - self._odom_s)
        self._twist = Twist2D(v, w)
        self._odom_s = now

    def _fault(self, reason: str) -> None:
        """Stop both wheels and remember why (call with the lock held)."""
        if reason in self._faults:
            return
        if len(self._faults) >= MAX_FAULTS:
            self.stats.faults_dropped += 1
            return  # already stopped, for the reasons kept
        log.error("stopping the robot: %s", reason)
        self._faults.append(reason)
        self.stats.faults.append(reason)
        self._quick_stop_all()

    def _quick_stop_all(self) -> None:
        """Quick stop on both wheels (call with the lock held)."""
        self._quick_stopping, self._running = True, False
        if self._wheels is not None and not self._closed:
            for wheel in self._wheels:
                try:
                    self._send(wheel, Cw.QUICK_STOP, 0.0)
                except Exception as exc:
                    log.warning("quick stop of %s failed: %s", wheel.name, exc)

    def _supervise(self) -> None:
        period_s = min(0.02, self.settings.heartbeat_timeout_s / 5)
        while not self._stop.wait(period_s):
            with self._lock:
                if self._wheels is None or self._closed:
                    continue
                now = time.monotonic()
                for wheel in self._wheels:
                    if now - wheel.last_beat_s > self.settings.heartbeat_timeout_s:
                        if f"{wheel.name} drive heartbeat lost" not in self._faults:
                            self.stats.heartbeat_losses += 1
                        self._fault(f"{wheel.name} drive heartbeat lost")


def _clean_slate(node: canopen.RemoteNode) -> None:
    """Forget what corrupt or forged frames left in `canopen`'s state before a connect: a
    heartbeat state no node may send (the library keeps it, then fails on it with a
    KeyError at the next state change it logs), and SDO responses nobody asked for (the
    next transfer would take one for its answer).
    """
    if node.nmt._state not in canopen.nmt.NMT_STATES:  # the library's own attribute
        node.nmt._state = 0x7F  # pre-operational: what connect() sets next anyway
    responses = node.sdo.responses
    while not responses.empty():
        responses.get_nowait()


def _stopped_itself(statusword: int) -> bool:
    """Whether a drive that was running reports QUICK STOP ACTIVE or SWITCH ON DISABLED."""
    return (
        statusword & STATE_MASK == QUICK_STOP_ACTIVE
        or statusword & SWITCH_ON_DISABLED_MASK == SWITCH_ON_DISABLED
    )
