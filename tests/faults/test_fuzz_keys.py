"""A fuzzer for every key a process subscribes to: first every field of its message at
each boundary value of its type, one at a time; then random, truncated, bit-flipped,
schema-shaped extreme and perturbed payloads (hypothesis strategies built from the wire
models), into
the real receiving code of the agent, the world, a host daemon and the launcher. After
each payload the process goes on (the agent steps, the world ticks); every few, its
commands are held to the run's limits and its log, metrics and status are written.

CI runs a bounded sample of each (FUZZ_EXAMPLES per key); `bench/bench_fuzz.py` runs the
10^5-per-key campaign recorded in docs/RELIABILITY.md.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from receivers import (
    AgentUnderTest,
    DaemonUnderTest,
    DriverAgentUnderTest,
    LauncherUnderTest,
    WorldUnderTest,
    campaign,
    sweep,
)

from phalanx.core.runlog import ESTIMATE_POSE, SIMULATED_POSE
from phalanx.wire.codec import encode
from phalanx.wire.messages import ScanMessage

FUZZ_EXAMPLES = int(os.environ.get("PHALANX_FUZZ_EXAMPLES", "150"))
AGENT_KEYS = ("agent/flags", "agent/state", "agent/sense", "agent/operator")
POSITIONING_KEYS = ("agent/fix", "agent/relative")
WORLD_KEYS = ("world/cmd", "world/state", "world/event", "world/report", "world/leader")
OBSERVING_KEYS = ("world/truth", "world/fix")
DAEMON_KEYS = ("daemon/spawn", "daemon/stop", "daemon/status")
LAUNCHER_KEYS = ("launcher/state", "launcher/log", "launcher/reply")


# In lockstep an agent hears every state in the world's frames (fuzzed with the frame)
# and no flags; in real time flags and its path's states through rings.
AGENT_CASES = [("realtime", k) for k in AGENT_KEYS] + [
    ("lockstep", k) for k in AGENT_KEYS if k not in ("agent/flags", "agent/state")
]


@pytest.mark.parametrize(("clock", "key"), AGENT_CASES)
def test_no_payload_crashes_an_agent_or_moves_it_beyond_its_limits(clock: str, key: str) -> None:
    agent = AgentUnderTest(clock=clock)
    swept = sweep(agent, key, check_every=25)
    seed = zlib.crc32(f"{key}/{clock}".encode())
    sent = campaign(agent, key, FUZZ_EXAMPLES, seed=seed, check_every=25)
    assert sent == FUZZ_EXAMPLES
    assert agent.steps >= swept + sent  # it stepped on every tick, whatever came between
    assert agent.session.stats.dropped > 0  # and what it refused, it counted
    if key == "agent/operator":  # valid commands got through to the agent
        assert agent.runtime.operator.heard > 0


def test_no_scan_crashes_a_navigating_agent_or_reaches_its_map_unchecked() -> None:
    agent = AgentUnderTest(navigating=True)
    swept = sweep(agent, "agent/scan", check_every=25)
    sent = campaign(agent, "agent/scan", FUZZ_EXAMPLES, seed=zlib.crc32(b"agent/scan"),
                    check_every=25)  # fmt: skip
    assert sent == FUZZ_EXAMPLES
    assert agent.steps >= swept + sent
    assert agent.session.stats.dropped > 0
    assert agent.runtime.scans.heard > 0  # valid scans got through
    grid = agent.runtime.agent.parts.planner.fleet
    assert grid is not None
    assert grid.scans_added > agent.steps  # into the map, with its own


@pytest.mark.parametrize("key", POSITIONING_KEYS)
def test_no_positioning_payload_crashes_an_agent_on_a_driver(key: str) -> None:
    agent = DriverAgentUnderTest()
    try:
        swept = sweep(agent, key, check_every=25)
        sent = campaign(agent, key, FUZZ_EXAMPLES, seed=zlib.crc32(key.encode()), check_every=25)
        assert sent == FUZZ_EXAMPLES
        assert agent.steps >= swept + sent
        assert agent.session.stats.dropped > 0
        assert agent.inbox.received > 0  # valid fixes reached the estimator
    finally:
        agent.close()


@pytest.mark.parametrize("key", WORLD_KEYS)
def test_no_payload_crashes_the_world_or_spoils_its_results(key: str) -> None:
    world = WorldUnderTest(clock="realtime" if key == "world/cmd" else "lockstep")
    assert sweep(world, key, check_every=100)
    assert campaign(world, key, FUZZ_EXAMPLES, seed=zlib.crc32(key.encode()), check_every=50)
    assert world.session.stats.dropped > 0


@pytest.mark.parametrize("key", OBSERVING_KEYS)
def test_no_pose_of_a_robot_on_a_driver_crashes_the_world_or_spoils_its_record(key: str) -> None:
    """The world records robots that move on their own from what it hears of them: a
    simulator's true pose, motion capture."""
    world = WorldUnderTest(clock="realtime", observed=("r2", "r3"))
    assert sweep(world, key, check_every=100)
    assert campaign(world, key, FUZZ_EXAMPLES, seed=zlib.crc32(key.encode()), check_every=50)
    assert world.session.stats.dropped > 0
    log = world.world._log()
    heard = "r2" if key == "world/truth" else "r3"
    assert log.pose_sources[heard] not in (SIMULATED_POSE, ESTIMATE_POSE)
    trace = log.traces[heard]  # every pose it took is finite and within the arena
    assert np.isfinite(trace.x_m).all()
    assert (np.abs(trace.x_m) <= 1e4).all()


@pytest.mark.parametrize("key", DAEMON_KEYS)
def test_no_request_crashes_a_host_daemon_or_starts_anything(key: str, tmp_path: Path) -> None:
    daemon = DaemonUnderTest(tmp_path)
    swept = sweep(daemon, key)
    assert campaign(daemon, key, FUZZ_EXAMPLES, seed=zlib.crc32(key.encode()))
    assert daemon.daemon.requests == swept + FUZZ_EXAMPLES  # every request answered
    if key == "daemon/spawn":  # and none could start anything (no payload holds the digest)
        assert daemon.daemon.refused == swept + FUZZ_EXAMPLES


@pytest.mark.parametrize("key", LAUNCHER_KEYS)
def test_no_payload_crashes_the_launcher(key: str) -> None:
    launcher: Any = LauncherUnderTest()
    assert sweep(launcher, key)
    assert campaign(launcher, key, FUZZ_EXAMPLES, seed=zlib.crc32(key.encode()))


def test_a_scan_of_another_ring_than_the_fleets_is_dropped_and_counted() -> None:
    """The map reads every robot's scan with its own robot's ring (16 sonars): a scan
    of 24 ranges, each with its echo flag, is well formed but no scan of this fleet. It
    is dropped and counted; the agent steps on, and takes the next scan of 16."""
    agent = AgentUnderTest(navigating=True)
    _, key, _ = agent.keys()["agent/scan"]
    for ring, taken in ((24, False), (16, True)):
        scan = ScanMessage(
            robot_id="r1", stamp_s=agent.t_s, x_m=0.0, y_m=0.0, theta_rad=0.0,
            ranges_m=(2.0,) * ring, echo=(True,) * ring,
        )  # fmt: skip
        dropped, heard, steps = agent.session.stats.dropped, agent.runtime.scans.heard, agent.steps
        agent.inject(key, encode(scan))
        agent.step()
        assert agent.steps == steps + 1
        assert agent.session.stats.dropped == dropped + (not taken)
        assert agent.runtime.scans.heard == heard + taken
