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
        publisher = session._publishers[robot_key("qos", "r2", "state")]
        assert publisher.congestion_control == congestion
