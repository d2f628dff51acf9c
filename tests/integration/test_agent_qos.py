"""What an agent process asks of Zenoh for its state, on a real session: in lockstep the
state is its answer to the world's frame (the world waits for it and relays it), so it
is published as the command is, with BLOCK congestion control; in real time the newest
state is what counts, and one the link has no room for is dropped (DROP)."""

from __future__ import annotations

import pytest
import zenoh
from agentlab import framed_agent

from phalanx.runtime.agent import ClockMode
from phalanx.wire.keys import robot_key
from phalanx.wire.messages import AgentEvent
from phalanx.wire.transport import TransportConfig, free_tcp_port, loopback_endpoint, open_session

pytestmark = pytest.mark.integration


@pytest.mark.parametrize(
    ("clock", "congestion"),
    [("lockstep", zenoh.CongestionControl.BLOCK), ("realtime", zenoh.CongestionControl.DROP)],
)
def test_an_agents_state_goes_with_block_in_lockstep_and_drop_in_real_time(
    clock: ClockMode, congestion: zenoh.CongestionControl
) -> None:
    with framed_agent("qos", clock) as it:
        assert it.frames_until(lambda: it.runtime.steps >= 3, 20.0)  # it has answered
        session = it.runtime._session
        assert session is not None
        publisher = session._publishers[robot_key("qos", "r2", "state"), clock == "lockstep"]
        assert publisher.congestion_control == congestion


def test_one_key_published_both_ways_keeps_each_way() -> None:
    """A session keeps a publisher per key and congestion control: a key put with BLOCK
    once and with DROP once is put each time the way asked, not the first way for good."""
    event = AgentEvent(robot_id="r1", t_s=1.0, source="HOLD", target="NAVIGATE", reason="x")
    key = robot_key("qos", "r1", "event")
    listen = (loopback_endpoint(free_tcp_port()),)
    with open_session(TransportConfig(mode="router", listen=listen)) as session:
        session.publish(key, event, reliable_block=True)
        session.publish(key, event)
        block, drop = session._publishers[key, True], session._publishers[key, False]
        assert block.congestion_control == zenoh.CongestionControl.BLOCK
        assert drop.congestion_control == zenoh.CongestionControl.DROP
