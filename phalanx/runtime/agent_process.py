"""One robot's agent process, built from its spec (`phalanx.runtime.process_spec`) and run:
the one place that assembles it. A simulated robot steps on the world's frames
(`WorldLink`); a robot on a driver (opened through the driver registry) keeps its own
clock (`EpochClock`) and reaches its robot through the safety wrapper (`SafeDriver`,
`DriverIO`), with its positioning fixes and camera. `phalanx agent` parses its options
(or reads a spec) and calls `run_agent`, whoever started it.
"""

from __future__ import annotations

import time

from phalanx.core.compiled import numpy_unless_asked
from phalanx.core.config import Scenario
from phalanx.core.config_files import apply_overrides, load_robot, load_scenario
from phalanx.core.errors import ConfigError, DriverError, DriverUnavailable
from phalanx.core.limits import safety_limits
from phalanx.core.robot_params import RobotParams
from phalanx.drivers import open_driver
from phalanx.drivers.base import Driver
from phalanx.drivers.safety import SafeDriver
from phalanx.runtime.agent import AgentRuntime, RuntimeOptions
from phalanx.runtime.clock import EpochClock
from phalanx.runtime.exits import EXIT_FINISHED, EXIT_RUN_CUT_SHORT, EXIT_WORLD_LOST
from phalanx.runtime.positioning import PositioningInbox, open_camera
from phalanx.runtime.process_spec import AgentSpec, DriverChoice, telemetry_for
from phalanx.runtime.robot_io import DriverIO, WorldLink
from phalanx.runtime.signals import Stoppable
from phalanx.telemetry.stream import Telemetry
from phalanx.wire.bounds import FleetBounds
from phalanx.wire.messages import AgentReport

CONNECT_TIMEOUT_S = 15.0  # a robot (or its simulator) still coming up is waited for


def run_agent(spec: AgentSpec, *, stop: Stoppable) -> tuple[AgentReport, int]:
    """Build the agent `spec` describes and run it to its end: its report, and its exit
    code (`phalanx.runtime.exits`). ConfigError for a spec its scenario does not fit;
    DriverUnavailable if the driver's library is missing or the robot never answers.
    """
    numpy_unless_asked()
    scenario, robot = agent_scenario(spec)
    driver = _open(spec.driver, robot)
    with telemetry_for(spec.telemetry, robot_id=spec.robot_id) as telemetry:
        if driver is None:
            return _simulated(spec, scenario, robot, stop=stop, telemetry=telemetry)
        return _on_driver(spec, scenario, robot, driver, stop=stop, telemetry=telemetry)


def agent_scenario(spec: AgentSpec) -> tuple[Scenario, RobotParams]:
    """The spec's scenario (its overrides applied) and robot parameters; ConfigError if
    the spec's robot is not in it.
    """
    config = load_scenario(spec.scenario)
    if spec.overrides:
        config = apply_overrides(config, list(spec.overrides), source=str(spec.scenario))
    if spec.robot_id not in {r.id for r in config.robots}:
        raise ConfigError(f"robot {spec.robot_id!r} is not in {spec.scenario}")
    return config, load_robot(config.robot)


def _open(choice: DriverChoice, robot: RobotParams) -> Driver | None:
    """The chosen driver for `robot`, built by the registry, not yet connected; None for
    a simulated robot (the world moves it).
    """
    if choice.settings is None:
        return None
    return open_driver(choice.name, choice.settings, robot=robot)


def _on_driver(
    spec: AgentSpec,
    scenario: Scenario,
    robot: RobotParams,
    driver: Driver,
    *,
    stop: Stoppable,
    telemetry: Telemetry | None,
) -> tuple[AgentReport, int]:
    """A robot on a driver: its own clock from the shared epoch, its own readings."""
    options = RuntimeOptions(fleet=spec.fleet, transport=spec.transport, clock="realtime")
    limits = safety_limits(robot, scenario.limits, watchdog_s=spec.watchdog_s)
    safe = SafeDriver(driver, limits)
    connect_with_retry(safe, stop)
    steps = round(scenario.duration_s / scenario.dt_s)
    rid = spec.robot_id
    with safe:
        epoch_s = spec.epoch_s or time.time()
        ticks = EpochClock(epoch_s=epoch_s, dt_s=scenario.dt_s, steps=steps)
        inbox = PositioningInbox(spec.fleet, rid, epoch_s=epoch_s)
        if spec.camera is not None:
            inbox.camera = open_camera(spec.camera, rid, scenario, epoch_s=epoch_s)
        origin = scenario.start_pose(rid)
        io = DriverIO(
            safe, robot, origin=origin, positioning=inbox, robot_id=rid, fleet=spec.fleet,
            epoch_s=epoch_s,
        )  # fmt: skip
        runtime = AgentRuntime(
            rid, scenario, robot, options, clock=ticks, io=io, telemetry=telemetry
        )
        return runtime.run(stop), EXIT_FINISHED


def _simulated(
    spec: AgentSpec,
    scenario: Scenario,
    robot: RobotParams,
    *,
    stop: Stoppable,
    telemetry: Telemetry | None,
) -> tuple[AgentReport, int]:
    """A simulated robot: the world's frames are its ticks and its readings."""
    options = RuntimeOptions(fleet=spec.fleet, transport=spec.transport, clock=spec.clock)
    ids = tuple(r.id for r in scenario.robots)
    link = WorldLink(
        spec.fleet, spec.robot_id, frame_timeout_s=spec.frame_timeout_s, robot_ids=ids,
        bounds=FleetBounds.of(scenario, robot),
    )  # fmt: skip
    runtime = AgentRuntime(
        spec.robot_id, scenario, robot, options, clock=link, io=link, telemetry=telemetry
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
