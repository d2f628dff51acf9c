"""Zenoh's low-latency transport, as `phalanx up` runs a fleet on one machine: messages
cross it, one too big for a batch is refused before it can reset the link, and every
process `phalanx up` starts asks for it."""

from __future__ import annotations

import logging
import threading

import pytest

from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.runtime.local_fleet import Child, UpOptions, plan
from phalanx.wire.messages import AgentEvent
from phalanx.wire.transport import (
    LOWLATENCY_MAX_BYTES,
    PEER_LOWLATENCY,
    TransportConfig,
    free_tcp_port,
    loopback_endpoint,
    open_session,
    zenoh_config,
)

pytestmark = pytest.mark.integration
WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"


def _lowlatency(child: Child) -> bool:
    """Whether `phalanx up` gives the process the low-latency transport: the world by its
    command line, an agent in its spec.
    """
    return child.spec.transport.lowlatency if child.spec else "--lowlatency" in child.argv


def _event(reason: str) -> AgentEvent:
    return AgentEvent(robot_id="r1", t_s=1.0, source="HOLD", target="NAVIGATE", reason=reason)


def test_the_config_turns_priorities_off_with_it() -> None:
    """Zenoh refuses the low-latency transport with priorities (QoS) on."""
    on = zenoh_config(TransportConfig(lowlatency=True))
    off = zenoh_config(TransportConfig())
    assert on.get_json("transport/unicast/lowlatency") == "true"
    assert on.get_json("transport/unicast/qos/enabled") == "false"
    assert off.get_json("transport/unicast/lowlatency") == "false"
    assert off.get_json("transport/unicast/qos/enabled") == "true"


def test_a_peer_on_it_is_told_to_use_a_router(caplog: pytest.LogCaptureFixture) -> None:
    """A large mesh of peers on it can hang Zenoh's declarations: a peer is warned, a
    router (as `phalanx up` runs it) is not."""
    with caplog.at_level(logging.WARNING, logger="phalanx.transport"):
        for mode in ("router", "peer"):
            listen = (loopback_endpoint(free_tcp_port()),)
            with open_session(TransportConfig(mode=mode, listen=listen, lowlatency=True)):
                pass
            assert (PEER_LOWLATENCY in caplog.text) == (mode == "peer"), mode


def test_messages_cross_and_an_oversized_status_is_refused_not_sent() -> None:
    """A status reply over a batch would be lost and reset the link: an error is sent in
    its place, and the link carries the next message."""
    endpoint = loopback_endpoint(free_tcp_port())
    router = TransportConfig(mode="router", listen=(endpoint,), lowlatency=True)
    client = TransportConfig(mode="client", connect=(endpoint,), lowlatency=True)
    got: list[str] = []
    arrived = threading.Event()

    def on_event(_key: str, event: AgentEvent) -> None:
        got.append(event.reason)
        arrived.set()

    with open_session(router) as world, open_session(client) as robot:
        world.subscribe("phalanx/t/robots/r1/event", AgentEvent, on_event)
        for _ in range(50):  # until the subscription has reached the client
            robot.publish("phalanx/t/robots/r1/event", _event("first"), reliable_block=True)
            if arrived.wait(0.1):
                break
        assert "first" in got
        sizes = {"small": 10, "huge": LOWLATENCY_MAX_BYTES}
        for name, size in sizes.items():
            world.serve_status(f"phalanx/t/status/{name}", lambda n=size: {"pad": "x" * n})
        assert robot.query_status("phalanx/t/status/small") == [{"pad": "x" * 10}]
        (reply,) = robot.query_status("phalanx/t/status/huge")
        assert "at most 60000 bytes" in reply["error"]
        arrived.clear()
        robot.publish("phalanx/t/robots/r1/event", _event("after"), reliable_block=True)
        assert arrived.wait(5.0)  # the link was never reset
        assert got[-1] == "after"


def test_up_starts_every_process_on_it() -> None:
    world, *agents = plan(WEDGE, load_scenario(WEDGE), UpOptions(fleet="ll"))
    assert len(agents) == 3
    assert "--lowlatency" in world.argv
    for agent in agents:
        assert agent.spec is not None, agent.name
        assert agent.spec.transport.lowlatency, agent.name


def test_a_fleet_whose_lockstep_frames_do_not_fit_is_refused_or_run_without_it() -> None:
    # A lockstep frame carries every other robot's state: past about 350 robots it is
    # over the low-latency transport's message size.
    from phalanx.core.config_files import load_robot
    from phalanx.core.errors import ConfigError
    from phalanx.core.scenarios import grid_scenario
    from phalanx.runtime.world_process import WorldOptions, WorldProcess

    big = grid_scenario(load_scenario(WEDGE), 400)
    robot = load_robot(big.robot)
    options = WorldOptions(fleet="ll", transport=TransportConfig(lowlatency=True))
    with pytest.raises(ConfigError, match="without --lowlatency"):
        WorldProcess(big, robot, options)
    for child in plan(WEDGE, big, UpOptions(fleet="ll")):  # `phalanx up` leaves it off
        assert not _lowlatency(child), child.name
    realtime = plan(WEDGE, big, UpOptions(fleet="ll", clock="realtime"))
    assert all(_lowlatency(child) for child in realtime)  # no frames with states
    fits = grid_scenario(load_scenario(WEDGE), 300)
    WorldProcess(fits, robot, options)  # (300 robots fit)
