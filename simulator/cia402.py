"""Simulated CiA 402 drives on a CAN bus, for tests and demos of the `canopen` backend.

Each `SimulatedDrive` is a canopen LocalNode with an object dictionary covering what the
backend touches (built from an EDS text in `drive_eds`), the CiA 402 state machine driven
by the controlword (by SDO or by RPDO1), a first-order motor model in profile velocity
mode, TPDO1 (statusword, velocity actual) every 20 ms, a heartbeat producer, and fault
injection: a lost heartbeat (the drive falls silent, as if unplugged), a drive fault
(FAULT state and an EMCY), cleared by a fault reset, and an emergency-stop input (the
drive quick-stops on its own and refuses to enable while it is pressed). The CiA 402
facts it follows: docs/HARDWARE.md.
"""

from __future__ import annotations

import struct
import threading
import time
from dataclasses import dataclass, field

import canopen

from phalanx.core.errors import DriverError
from phalanx.core.lifecycle import Closing
from phalanx.protocols.cia402 import (
    SW_FAULT,
    SW_OPERATION_ENABLED,
    SW_QUICK_STOP,
    SW_READY,
    SW_SWITCH_ON_DISABLED,
    SW_SWITCHED_ON,
    SW_TARGET_REACHED,
    Cw,
    drive_od,
)


def next_state(state: int, controlword: int, previous_controlword: int) -> int:
    """The drive's next statusword state after `controlword` (CiA 402 figure, simplified)."""
    if state == SW_FAULT:
        rising_reset = controlword & 0x80 and not previous_controlword & 0x80
        return SW_SWITCH_ON_DISABLED if rising_reset else SW_FAULT
    if controlword & 0x02 == 0:  # disable voltage
        return SW_SWITCH_ON_DISABLED
    if controlword & 0x04 == 0:  # quick stop (bit 2 low)
        return SW_QUICK_STOP if state == SW_OPERATION_ENABLED else SW_SWITCH_ON_DISABLED
    command = controlword & 0x0F
    if command == Cw.SHUTDOWN:
        return SW_READY
    if command == Cw.SWITCH_ON:
        return (
            SW_SWITCHED_ON if state in (SW_READY, SW_SWITCHED_ON, SW_OPERATION_ENABLED) else state
        )
    if command == Cw.ENABLE_OPERATION:
        if state in (SW_SWITCHED_ON, SW_OPERATION_ENABLED, SW_QUICK_STOP):
            return SW_OPERATION_ENABLED
        return state
    return state


@dataclass
class DriveStats:
    """What a simulated drive received and did."""

    rpdos: int = 0
    tpdos: int = 0
    sdo_controlwords: int = 0
    faults: int = 0
    last_target: int = 0
    targets: list[int] = field(default_factory=list)


class SimulatedDrive:
    """One CiA 402 drive: LocalNode, state machine, motor model, faults."""

    def __init__(
        self, network: canopen.Network, node_id: int, *, time_constant_s: float = 0.05
    ) -> None:
        self.node_id = node_id
        self.tau_s = time_constant_s
        self.node = network.create_node(node_id, drive_od(node_id))
        self.stats = DriveStats()
        self._lock = threading.Lock()
        self._state = SW_SWITCH_ON_DISABLED
        self._controlword = 0
        self._target = 0
        self._actual = 0.0
        self._silent = False
        self._estop = False  # the drive's emergency-stop input
        self.node.add_write_callback(self._on_sdo_write)
        self.node.tpdo.read(from_od=True)
        self.node.rpdo.read(from_od=True)
        self.node.rpdo[1].add_callback(self._on_rpdo)
        self.node.nmt.state = "PRE-OPERATIONAL"  # boot: starts the heartbeat producer
        self._publish()

    # -- inputs ----------------------------------------------------------------------

    def _on_sdo_write(self, index: int, subindex: int, od: object, data: bytes) -> None:
        del subindex, od
        if index == 0x6040:
            with self._lock:
                self.stats.sdo_controlwords += 1
                self._apply_controlword(struct.unpack("<H", data)[0])
        elif index == 0x60FF:
            with self._lock:
                self._target = struct.unpack("<i", data)[0]

    def _on_rpdo(self, pdo: canopen.pdo.PdoMap) -> None:
        if self._silent or self.node.nmt.state != "OPERATIONAL":
            return  # PDOs only count in OPERATIONAL
        with self._lock:
            self.stats.rpdos += 1
            self._apply_controlword(int(pdo["Controlword"].raw))
            self._target = int(pdo["Target velocity"].raw)
            self.stats.last_target = self._target

    def _apply_controlword(self, controlword: int) -> None:
        state = next_state(self._state, controlword, self._controlword)
        if self._estop and state == SW_OPERATION_ENABLED:
            state = self._state  # no enabling while the E-stop input is pressed
        self._state = state
        self._controlword = controlword
        if self._state == SW_SWITCH_ON_DISABLED:
            self.node.sdo[0x603F].raw = 0  # fault reset clears the error code

    # -- model -----------------------------------------------------------------------

    def step(self, dt_s: float) -> None:
        """Advance the motor by `dt_s` and publish statusword and velocity."""
        with self._lock:
            target = self._target if self._state == SW_OPERATION_ENABLED else 0
            alpha = min(1.0, dt_s / self.tau_s)
            self._actual += (target - self._actual) * alpha
            if self._state == SW_QUICK_STOP and abs(self._actual) < 1:
                self._state = SW_SWITCH_ON_DISABLED
        self._publish()

    def _publish(self) -> None:
        with self._lock:
            status = self._state
            if self._state == SW_OPERATION_ENABLED and abs(self._actual - self._target) < 1:
                status |= SW_TARGET_REACHED
            actual = round(self._actual)
        self.node.sdo[0x6041].raw = status
        self.node.sdo[0x606C].raw = actual
        if self._silent or self.node.nmt.state != "OPERATIONAL":
            return
        tpdo = self.node.tpdo[1]
        tpdo["Statusword"].raw = status
        tpdo["Velocity actual value"].raw = actual
        tpdo.transmit()
        self.stats.tpdos += 1

    @property
    def state(self) -> int:
        """The statusword state bits."""
        with self._lock:
            return self._state

    @property
    def velocity(self) -> float:
        """Velocity actual, drive units."""
        with self._lock:
            return self._actual

    @property
    def target(self) -> int:
        """Target velocity, drive units."""
        with self._lock:
            return self._target

    # -- faults ----------------------------------------------------------------------

    def lose_heartbeat(self) -> None:
        """Fall silent: no heartbeat, no PDOs, as if the drive's cable were pulled."""
        self._silent = True
        self.node.nmt.stop_heartbeat()

    def restore(self) -> None:
        """Talk again after `lose_heartbeat`."""
        self._silent = False
        self.node.nmt.start_heartbeat(int(self.node.sdo[0x1017].raw))

    def press_estop(self, pressed: bool = True) -> None:
        """The drive's emergency-stop input: pressed, it quick-stops the motor (QUICK STOP
        ACTIVE, then SWITCH ON DISABLED at a standstill) and refuses to enable; released,
        the drive stays disabled until the controller enables it again.
        """
        with self._lock:
            self._estop = pressed
            if pressed and self._state == SW_OPERATION_ENABLED:
                self._state = SW_QUICK_STOP

    def inject_fault(self, code: int = 0x2310) -> None:
        """Go to FAULT (motor coasts down) and send an EMCY with `code` (0x2310: current)."""
        with self._lock:
            self._state = SW_FAULT
            self.stats.faults += 1
        self.node.sdo[0x603F].raw = code
        self.node.emcy.send(code, 0x01)


class SimulatedDiffDrive(Closing):
    """Two simulated drives (left, right) on a python-can bus, stepped at `rate_hz` (the
    TPDO rate) by one thread.
    """

    def __init__(
        self,
        channel: str,
        *,
        interface: str = "virtual",
        left_node_id: int = 1,
        right_node_id: int = 2,
        rate_hz: float = 50.0,
    ) -> None:
        self.network = canopen.Network()
        try:
            self.network.connect(interface=interface, channel=channel, receive_own_messages=False)
        except Exception as exc:  # python-can raises many kinds
            raise DriverError(f"cannot open CAN {interface}:{channel}: {exc}") from exc
        self.left = SimulatedDrive(self.network, left_node_id)
        self.right = SimulatedDrive(self.network, right_node_id)
        self.rate_hz = rate_hz
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="cia402-sim", daemon=True)
        self._thread.start()
        self._closed = False

    @property
    def drives(self) -> tuple[SimulatedDrive, SimulatedDrive]:
        """(left, right)."""
        return self.left, self.right

    def _run(self) -> None:
        period_s = 1.0 / self.rate_hz
        last = time.monotonic()
        while not self._stop.wait(period_s):
            now = time.monotonic()
            for drive in self.drives:
                drive.step(now - last)
            last = now

    def close(self) -> None:
        """Stop the model and leave the bus (safe twice)."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self._thread.join(2.0)
        for drive in self.drives:
            drive.node.nmt.stop_heartbeat()
        self.network.disconnect()
