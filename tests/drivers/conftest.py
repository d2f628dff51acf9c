"""Every driver backend, ready to test: the `rig` fixture yields each backend (not yet
connected) and the robot side behind it (emulator or simulated drives)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from typing import Any

import pytest

from phalanx.core.config_files import load_robot
from phalanx.core.geometry import Twist2D
from phalanx.core.limits import SafetyLimits
from phalanx.drivers.arcos import ArcosDriver, ArcosSettings
from phalanx.drivers.base import Driver
from phalanx.drivers.canopen import CanopenDriver, CanopenSettings
from phalanx.drivers.sim import SimDriver
from phalanx.simulator.arcos_emulator import ArcosEmulator, PtyLink, TcpLink
from phalanx.simulator.cia402 import SimulatedDiffDrive

ROBOT = load_robot("p3dx")
LIMITS = SafetyLimits(v_max_mps=0.3, omega_max_radps=math.radians(40.0), watchdog_s=0.3)


@dataclass
class Rig:
    """A backend under test and the thing on the other end of its link."""

    driver: Driver
    robot_side: Any = None
    limits: SafetyLimits = LIMITS
    zero_commanded: Callable[[], bool] | None = None  # the robot itself was told to stop


@contextmanager
def sim_rig() -> Iterator[Rig]:
    yield Rig(SimDriver(ROBOT))


@contextmanager
def arcos_pty_rig() -> Iterator[Rig]:
    link = PtyLink()
    with ArcosEmulator(link, ROBOT) as emulator:
        yield Rig(
            ArcosDriver(ArcosSettings(port=link.device), robot=ROBOT),
            emulator,
            LIMITS,
            _zero(emulator),
        )


@contextmanager
def arcos_tcp_rig() -> Iterator[Rig]:
    link = TcpLink(0)
    with ArcosEmulator(link, ROBOT) as emulator:
        driver = ArcosDriver(ArcosSettings(tcp=f"127.0.0.1:{link.port}"), robot=ROBOT)
        yield Rig(driver, emulator, LIMITS, _zero(emulator))


def _zero(emulator: ArcosEmulator) -> Callable[[], bool]:
    return lambda: emulator.body.state().setpoint == Twist2D(0.0, 0.0)


@contextmanager
def canopen_rig(request: pytest.FixtureRequest) -> Iterator[Rig]:
    channel = f"conf-{request.node.name}"  # a virtual bus of its own
    with SimulatedDiffDrive(channel) as drives:
        driver = CanopenDriver(CanopenSettings(interface="virtual", channel=channel), robot=ROBOT)

        def zero() -> bool:
            return all(d.target == 0 for d in drives.drives)

        yield Rig(driver, drives, LIMITS, zero)


RIGS: dict[str, Callable[[pytest.FixtureRequest], AbstractContextManager[Rig]]] = {
    "sim": lambda _r: sim_rig(),
    "arcos-pty": lambda _r: arcos_pty_rig(),
    "arcos-tcp": lambda _r: arcos_tcp_rig(),
    "canopen-virtual": canopen_rig,
}


@pytest.fixture(params=sorted(RIGS))
def rig(request: pytest.FixtureRequest) -> Iterator[Rig]:
    """Each backend in turn; closed afterwards whatever the test did."""
    with RIGS[request.param](request) as rig:
        try:
            yield rig
        finally:
            rig.driver.close()
