"""One robot's agent process, assembled: a simulated robot steps on the world's frames
(`WorldLink`); a robot on a driver keeps its own clock (`EpochClock`) and reaches its
robot through the safety wrapper (`SafeDriver`, `DriverIO`), with its positioning fixes
and camera. `phalanx agent` parses its options and calls `run_agent`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

from phalanx.core.config import Scenario
from phalanx.core.errors import DriverError, DriverUnavailable
from phalanx.core.limits import safety_limits
from phalanx.core.robot_params import RobotParams
from phalanx.drivers.base import Driver
from phalanx.drivers.safety import SafeDriver
from phalanx.runtime.agent import AgentRuntime, RuntimeOptions
from phalanx.runtime.clock import EpochClock
from phalanx.runtime.exits import EXIT_FINISHED, EXIT_RUN_CUT_SHORT, EXIT_WORLD_LOST
from phalanx.runtime.positioning import PositioningInbox, open_camera
from phalanx.runtime.robot_io import DriverIO, WorldLink
from phalanx.runtime.signals import Stoppable
from phalanx.telemetry.stream import Telemetry
from phalanx.wire.bounds import FleetBounds
from phalanx.wire.messages import AgentReport
from phalanx.wire.transport import TransportConfig

CONNECT_TIMEOUT_S = 15.0  # a robot (or its simulator) still coming up is waited for


@dataclass(frozen=True)
class AgentProcess:
    """How one robot's agent process runs (its robot and scenario apart)."""

    robot_id: str
    fleet: str
    transport: TransportConfig
    clock: Literal["lockstep", "realtime"] = "lockstep"
    epoch_s: float | None = None  # robots on drivers: Unix time of step 0 (None: now)
    watchdog_s: float = 0.5  # robots on drivers: no command this long, the robot stops
    frame_timeout_s: float = 30.0  # simulated robots: no frame this long, the world is gone
    camera: str | None = None  # robots on drivers: DEVICE=CALIBRATION.toml of a camera


def run_agent(
    process: AgentProcess,
    scenario: Scenario,
    robot: RobotParams,
    *,
    driver: Driver | None,
    stop: Stoppable,
    telemetry: Telemetry | None,
) -> tuple[AgentReport, int]:
    """Run the agent to its end: its report, and its exit code (`phalanx.runtime.exits`).
    `driver` None: a simulated robot, moved by the world. DriverUnavailable if the
    robot never answers.
    """
    if driver is None:
        return _simulated(process, scenario, robot, stop=stop, telemetry=telemetry)
    options = RuntimeOptions(fleet=process.fleet, transport=process.transport, clock="realtime")
    limits = safety_limits(robot, scenario.limits, watchdog_s=process.watchdog_s)
    safe = SafeDriver(driver, limits)
    connect_with_retry(safe, stop)
    steps = round(scenario.duration_s / scenario.dt_s)
    rid = process.robot_id
    with safe:
        epoch_s = process.epoch_s or time.time()
        ticks = EpochClock(epoch_s=epoch_s, dt_s=scenario.dt_s, steps=steps)
        inbox = PositioningInbox(process.fleet, rid, epoch_s=epoch_s)
        if process.camera is not None:
            inbox.camera = open_camera(process.camera, rid, scenario, epoch_s=epoch_s)
        origin = scenario.start_pose(rid)
        io = DriverIO(
            safe, robot, origin=origin, positioning=inbox, robot_id=rid, fleet=process.fleet,
            epoch_s=epoch_s,
        )  # fmt: skip
        runtime = AgentRuntime(
            rid, scenario, robot, options, clock=ticks, io=io, telemetry=telemetry
        )
        return runtime.run(stop), EXIT_FINISHED


def _simulated(
    process: AgentProcess,
    scenario: Scenario,
    robot: RobotParams,
    *,
    stop: Stoppable,
    telemetry: Telemetry | None,
) -> tuple[AgentReport, int]:
    """A simulated robot: the world's frames are its ticks and its readings."""
    options = RuntimeOptions(fleet=process.fleet, transport=process.transport, clock=process.clock)
    ids = tuple(r.id for r in scenario.robots)
    link = WorldLink(
        process.fleet, process.robot_id, frame_timeout_s=process.frame_timeout_s, robot_ids=ids,
        bounds=FleetBounds.of(scenario, robot),
    )  # fmt: skip
    runtime = AgentRuntime(
        process.robot_id, scenario, robot, options, clock=link, io=link, telemetry=telemetry
    )
    report = runtime.run(stop)
    if link.world_lost:
        return report, EXIT_WORLD_LOST
    if link.ending == "cut_short":
        return report, EXIT_RUN_CUT_SHORT
    return report, EXIT_FINISHED


def connect_with_retry(
    driver: SafeDriver, stop: Stoppable, timeout_s: float = CONNECT_TIMEOUT_S
) -> None:
    """Connect, retrying while the robot (or its simulator) comes up; DriverUnavailable
    if it never does.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            driver.connect()
            return
        except DriverError as exc:
            if time.monotonic() > deadline or stop.wait(0.5):
                raise DriverUnavailable(f"cannot reach the robot: {exc}") from exc
