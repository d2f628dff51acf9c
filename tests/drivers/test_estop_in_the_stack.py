"""An E-stop reaches the behaviour stack: on the robot's side (the P3DX's button on the
ARCOS emulator, a drive's emergency-stop input on the simulated CiA 402 drives) or latched
by the safety layer, it shows as `ESTOPPED` in the state the agent publishes over Zenoh on
the first control step after the driver reports it, and the agent's commands stop.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from typing import Any

import pytest
from agentlab import agent_on_driver
from fleetlab import wait_for

from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_robot, load_scenario
from phalanx.core.limits import safety_limits
from phalanx.core.states import State
from phalanx.drivers.safety import SafeDriver
from phalanx.runtime.clock import EpochClock
from phalanx.runtime.robot_io import DriverIO
from phalanx.simulator.arcos_emulator import ArcosEmulator
from phalanx.simulator.cia402 import SimulatedDiffDrive
from phalanx.wire.keys import robot_key
from phalanx.wire.messages import RobotState
from phalanx.wire.transport import TransportConfig, free_tcp_port, loopback_endpoint, open_session

pytestmark = [pytest.mark.drivers, pytest.mark.integration]
ROBOT = load_robot("p3dx")
WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
Rig = Any  # the `rig` fixture of conftest.py: .driver, .robot_side
SETTLE_S = 0.05  # a step reads the driver at most this long after its nominal instant


def _press(rig: Rig, safe: SafeDriver) -> Callable[[], None]:
    """What engages the E-stop of this rig's robot."""
    side = rig.robot_side
    if isinstance(side, ArcosEmulator):
        return side.press_estop  # the P3DX's own button: SIP flag bit 5
    if isinstance(side, SimulatedDiffDrive):
        return lambda: side.drives[0].press_estop()  # the left drive's E-stop input
    return safe.estop  # no robot side: the safety layer's latch


def test_an_estop_shows_in_the_published_state_on_the_next_step(rig: Rig) -> None:
    scenario = apply_overrides(load_scenario(WEDGE), ["duration_s=30"])
    port = free_tcp_port()
    transport = TransportConfig(listen=(loopback_endpoint(port),))
    listener = TransportConfig(mode="client", connect=(loopback_endpoint(port),))
    published: list[tuple[float, RobotState]] = []
    safe = SafeDriver(rig.driver, safety_limits(ROBOT, scenario.limits))
    with safe:
        epoch_s = time.time() + 0.5
        clock = EpochClock(epoch_s=epoch_s, dt_s=scenario.dt_s, steps=300)
        io = DriverIO(safe, ROBOT, origin=scenario.start_pose("r1"))
        with (
            agent_on_driver(scenario, ROBOT, io, clock, fleet="estop", transport=transport),
            open_session(listener) as session,
        ):
            session.subscribe(
                robot_key("estop", "r1", "state"),
                RobotState,
                lambda _k, s: published.append((epoch_s + s.stamp_s, s)),
            )
            assert wait_for(
                lambda: any(s.fsm_state == State.NAVIGATE for _, s in published),
                10.0,
                poll_s=0.005,
            ), [s.fsm_state for _, s in published]
            _press(rig, safe)()
            assert wait_for(lambda: safe.read_status().estopped, 2.0, poll_s=0.005)
            seen_s = time.time()
            assert wait_for(
                lambda: published[-1][0] > seen_s + 3 * scenario.dt_s, 5.0, poll_s=0.005
            )
    after = [(t_s, s) for t_s, s in published if t_s >= seen_s + SETTLE_S]
    first_t_s, _ = after[0]
    assert first_t_s <= seen_s + SETTLE_S + scenario.dt_s  # the next step is there
    assert all(s.fsm_state == State.ESTOPPED for _, s in after), [s.fsm_state for _, s in after]
    speeds = [s.v_mps for _, s in after]  # the agent brakes: its command only falls
    assert all(b <= a + 1e-9 for a, b in itertools.pairwise(speeds))
