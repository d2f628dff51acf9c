"""What an agent process asks of Zenoh for its state, on a real session: in lockstep the
state is its answer to the world's frame (the world waits for it and relays it), so it
is published as the command is, with BLOCK congestion control; in real time the newest
state is what counts, and one the link has no room for is dropped (DROP)."""

from __future__ import annotations

import itertools
import threading
import time

import pytest
import zenoh

from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_robot, load_scenario
from phalanx.runtime.agent import AgentRuntime, ClockMode, RuntimeOptions
from phalanx.runtime.robot_io import WorldLink
from phalanx.runtime.world_frames import sense_frame
from phalanx.simulator.world import World
from phalanx.wire.bounds import FleetBounds
from phalanx.wire.keys import robot_key
from phalanx.wire.transport import TransportConfig, free_tcp_port, loopback_endpoint, open_session

pytestmark = pytest.mark.integration

WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"


@pytest.mark.parametrize(
    ("clock", "congestion"),
    [("lockstep", zenoh.CongestionControl.BLOCK), ("realtime", zenoh.CongestionControl.DROP)],
)
def test_an_agents_state_goes_with_block_in_lockstep_and_drop_in_real_time(
    clock: ClockMode, congestion: zenoh.CongestionControl
) -> None:
    scenario = apply_overrides(load_scenario(WEDGE), ["duration_s=60"])
    robot = load_robot(scenario.robot)
    world = World.for_scenario(scenario, robot)
    endpoint = loopback_endpoint(free_tcp_port())
    options = RuntimeOptions(
        fleet="qos", transport=TransportConfig(mode="client", connect=(endpoint,)), clock=clock
    )
    ids = tuple(r.id for r in scenario.robots)
    link = WorldLink(
        "qos", "r2", frame_timeout_s=30.0, robot_ids=ids, bounds=FleetBounds.of(scenario, robot)
    )
    runtime = AgentRuntime("r2", scenario, robot, options, clock=link, io=link)
    stop = threading.Event()
    with open_session(TransportConfig(mode="router", listen=(endpoint,))) as fabric:
        agent = threading.Thread(target=runtime.run, args=(stop,))
        agent.start()
        try:
            deadline = time.monotonic() + 20.0
            for k in itertools.count():  # frames until the agent has answered a few
                if runtime.steps >= 3 or time.monotonic() > deadline:
                    break
                frame = sense_frame(world, "r2", k, scenario.dt_s)
                fabric.publish(robot_key("qos", "r2", "sense"), frame)
                time.sleep(scenario.dt_s)
            assert runtime.steps >= 3
            session = runtime._session
            assert session is not None
            publisher = session._publishers[robot_key("qos", "r2", "state")]
            assert publisher.congestion_control == congestion
        finally:
            stop.set()
            agent.join(15.0)
    assert not agent.is_alive()
