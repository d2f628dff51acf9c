"""One agent's process loop (`AgentRuntime`) run in a thread on a real Zenoh session:
robot r2 of the paper wedge stepped on the world's frames that a router session beside
it sends (`framed_agent`, what the integration tier's single-agent tests share), or r1
on its own clock over a driver (`agent_on_driver`, for the tests of the stack over a
robot)."""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from phalanx.core.config import Scenario
from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_robot, load_scenario
from phalanx.core.robot_params import RobotParams
from phalanx.runtime.agent import AgentRuntime, ClockMode, RuntimeOptions
from phalanx.runtime.clock import Clock
from phalanx.runtime.robot_io import RobotIO, WorldLink
from phalanx.runtime.world_frames import sense_frame
from phalanx.simulator.world import World
from phalanx.wire.bounds import FleetBounds
from phalanx.wire.keys import robot_key
from phalanx.wire.transport import (
    FleetSession,
    TransportConfig,
    free_tcp_port,
    loopback_endpoint,
    open_session,
)

WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"


@dataclass
class FramedAgent:
    """The agent under test and the router session that plays the world for it."""

    runtime: AgentRuntime
    fabric: FleetSession
    world: World
    fleet: str
    dt_s: float
    ticks: Iterator[int]

    def frames_until(self, done: Callable[[], bool], timeout_s: float) -> bool:
        """Send the agent a frame a tick until `done` holds (or `timeout_s` passes)."""
        rid = self.runtime.robot_id
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not done():
            frame = sense_frame(self.world, rid, next(self.ticks), self.dt_s)
            self.fabric.publish(robot_key(self.fleet, rid, "sense"), frame)
            time.sleep(self.dt_s)
        return done()


@contextmanager
def framed_agent(
    fleet: str, clock: ClockMode, *, lowlatency: bool = False
) -> Iterator[FramedAgent]:
    """Agent r2 on fleet `fleet` (`lowlatency`: both sessions on Zenoh's low-latency
    transport), its thread stopped and joined on the way out."""
    scenario = apply_overrides(load_scenario(WEDGE), ["duration_s=60"])
    robot = load_robot(scenario.robot)
    endpoint = loopback_endpoint(free_tcp_port())
    client = TransportConfig(mode="client", connect=(endpoint,), lowlatency=lowlatency)
    options = RuntimeOptions(fleet=fleet, transport=client, clock=clock)
    ids = tuple(r.id for r in scenario.robots)
    link = WorldLink(
        fleet, "r2", frame_timeout_s=30.0, robot_ids=ids, bounds=FleetBounds.of(scenario, robot)
    )
    runtime = AgentRuntime("r2", scenario, robot, options, clock=link, io=link)
    stop = threading.Event()
    router = TransportConfig(mode="router", listen=(endpoint,), lowlatency=lowlatency)
    with open_session(router) as fabric:
        agent = threading.Thread(target=runtime.run, args=(stop,))
        agent.start()
        try:
            world = World.for_scenario(scenario, robot)
            yield FramedAgent(runtime, fabric, world, fleet, scenario.dt_s, itertools.count())
        finally:
            stop.set()
            agent.join(15.0)
    assert not agent.is_alive()


@contextmanager
def agent_on_driver(
    scenario: Scenario,
    robot: RobotParams,
    io: RobotIO,
    clock: Clock,
    *,
    fleet: str,
    transport: TransportConfig | None = None,
) -> Iterator[AgentRuntime]:
    """Agent r1 of `scenario` in real time on `clock`, reaching its robot through `io`
    (a driver's), on a Zenoh session (`transport`; by default listening on a free
    loopback port), its loop run in a thread; stopped on the way out and joined, failing
    if the loop has not ended within 10 s."""
    transport = transport or TransportConfig(listen=(loopback_endpoint(free_tcp_port()),))
    options = RuntimeOptions(fleet=fleet, transport=transport, clock="realtime")
    runtime = AgentRuntime("r1", scenario, robot, options, clock=clock, io=io)
    stop = threading.Event()
    thread = threading.Thread(target=runtime.run, args=(stop,), daemon=True)
    thread.start()
    try:
        yield runtime
    finally:
        stop.set()
        thread.join(10.0)
    assert not thread.is_alive(), "the agent's loop did not end within 10 s"
