"""A flood of one robot's messages (row 6 of the security issue: 36 000 states of r1 in
10 s put the followers into HOLD): a rate-limited subscription takes from each key a few
times its sender's rate, drops the rest before decoding and counts it, so the flood
cannot push another key's messages out of a ring or off a Zenoh thread.

First the token buckets on a hand-driven clock, then real Zenoh sessions on loopback: a
flooder publishes r1's flags as fast as it can while r2 sends a few at its own rate; every
one of r2's arrives, through a ring (`subscribe_polled`) and through a callback
(`subscribe`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack

import pytest

from phalanx.wire.bounds import FleetBounds
from phalanx.wire.codec import DecodeStats, encode
from phalanx.wire.delivery import BURST, MAX_KEYS, RATE_HEADROOM, KeyBuckets, over_rate
from phalanx.wire.keys import robot_key, robots_key
from phalanx.wire.messages import RobotFlags
from phalanx.wire.transport import FleetSession, TransportConfig, free_tcp_port, loopback_endpoint

FLEET = "flood"
RATE_HZ = 10.0  # the scenario's control rate: one message per robot and step
R2_MESSAGES = BURST  # r2's own: within one burst, so their timing cannot matter
FLOOD_S = 60.0  # the flooder's bound (it stops once r2's are all in, and a ring more)
RING = 512  # more than the flood gets past the limit in a minute (BURST + 40 a second)
WAIT_S = 20.0


class Clock:
    """A clock the test moves by hand (s)."""

    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def _key(rid: str) -> str:
    return robot_key(FLEET, rid, "flags")


def test_a_bucket_takes_a_burst_then_a_few_times_the_rate_per_key() -> None:
    clock = Clock()
    buckets = KeyBuckets(RATE_HZ, clock=clock)
    assert [buckets.admit(_key("r1")) for _ in range(BURST + 3)] == [True] * BURST + [False] * 3
    assert all(buckets.admit(_key("r2")) for _ in range(BURST))  # r1's flood is r1's alone
    clock.now_s += 1.0 / RATE_HZ  # one step: RATE_HEADROOM more tokens
    taken = sum(buckets.admit(_key("r1")) for _ in range(100))
    assert taken == int(RATE_HEADROOM)
    steady = KeyBuckets(RATE_HZ, clock=clock)  # a sender at its rate is never dropped
    for _ in range(1000):
        clock.now_s += 1.0 / RATE_HZ
        assert steady.admit(_key("r3"))


def test_keys_outside_the_fleet_share_one_bucket_and_the_table_is_bounded() -> None:
    clock = Clock()
    bounds = FleetBounds(frozenset({"r1", "r2"}), v_max_mps=1.0, omega_max_radps=1.0,
                         t_max_s=100.0, dt_s=0.1, ticks=1000)  # fmt: skip
    buckets = KeyBuckets(RATE_HZ, bounds=bounds, clock=clock)
    strangers = [buckets.admit(_key(f"x{i}")) for i in range(BURST + 5)]
    assert strangers == [True] * BURST + [False] * 5
    assert buckets.admit(_key("r1"))
    open_table = KeyBuckets(RATE_HZ, clock=clock)
    admitted = sum(open_table.admit(_key(f"k{i}")) for i in range(3 * MAX_KEYS))
    assert admitted == MAX_KEYS + BURST  # the rest drew on the one shared bucket
    stats = DecodeStats()
    assert over_rate(open_table, _key("k99999"), stats, "RobotFlags")
    assert stats.rate_limited["RobotFlags"] == 1
    assert stats.dropped == 1
    with pytest.raises(ValueError, match="positive rate"):
        KeyBuckets(float("nan"))


def _flags(rid: str, seq: int) -> RobotFlags:
    return RobotFlags(robot_id=rid, seq=seq, stamp_s=0.0, fsm_state="FORMATION_TRACK")


@pytest.fixture
def sessions() -> Iterator[tuple[FleetSession, FleetSession, FleetSession, FleetSession]]:
    """A receiver (a router on loopback), a second receiver, a flooder and r2 (its clients)."""
    endpoint = loopback_endpoint(free_tcp_port())
    with ExitStack() as stack:
        listen = TransportConfig(mode="router", listen=(endpoint,), lease_ms=1000)
        receiver = stack.enter_context(FleetSession(listen))
        peer = TransportConfig(mode="client", connect=(endpoint,), lease_ms=1000)
        made = [stack.enter_context(FleetSession(peer)) for _ in range(3)]
        yield receiver, made[0], made[1], made[2]


def _flood(session: FleetSession, stop: threading.Event, sent: list[int]) -> None:
    payload = encode(_flags("r1", 1))
    deadline = time.monotonic() + FLOOD_S
    while not stop.is_set() and time.monotonic() < deadline:
        session.publish_raw(_key("r1"), payload)
        sent[0] += 1


def test_a_flooded_key_leaves_every_message_of_another_key_through(
    sessions: tuple[FleetSession, FleetSession, FleetSession, FleetSession],
) -> None:
    receiver, ear, flooder, r2 = sessions
    ring = receiver.subscribe_polled(robots_key(FLEET, "flags"), RobotFlags, RING,
                                     rate_hz=RATE_HZ)  # fmt: skip
    heard: list[RobotFlags] = []
    lock = threading.Lock()

    def on_flags(_key: str, flags: RobotFlags) -> None:
        with lock:
            heard.append(flags)

    ear.subscribe(robots_key(FLEET, "flags"), RobotFlags, on_flags, rate_hz=RATE_HZ)
    stop, sent = threading.Event(), [0]
    flood = threading.Thread(target=_flood, args=(flooder, stop, sent), daemon=True)
    flood.start()
    try:
        started = _wait(lambda: receiver.stats.rate_limited["RobotFlags"] > 0)
        for seq in range(R2_MESSAGES):  # during the flood
            r2.publish(_key("r2"), _flags("r2", seq), reliable_block=True)
            stop.wait(1.0 / RATE_HZ)
        r2_heard = _wait(lambda: len(_of("r2", heard, lock)) >= R2_MESSAGES)
        after = receiver.stats.rate_limited["RobotFlags"]  # then twice a ring of flood more
        _wait(lambda: receiver.stats.rate_limited["RobotFlags"] > after + 2 * RING)
    finally:
        stop.set()
        flood.join(WAIT_S)
    drained: list[RobotFlags] = []
    ring.drain(lambda _k, flags: drained.append(flags))

    assert started, "the flood never reached the receiver"
    assert sorted(f.seq for f in drained if f.robot_id == "r2") == list(range(R2_MESSAGES))
    assert r2_heard, [f.seq for f in _of("r2", heard, lock)]
    flood_in = sum(f.robot_id == "r1" for f in drained)
    limited = receiver.stats.rate_limited["RobotFlags"]
    assert 0 < flood_in < limited <= sent[0]  # most of the flood was dropped, and counted
    assert receiver.stats.ring_dropped["RobotFlags"] == 0
    assert ear.stats.rate_limited["RobotFlags"] > 0


def _of(rid: str, heard: list[RobotFlags], lock: threading.Lock) -> list[RobotFlags]:
    with lock:
        return [f for f in heard if f.robot_id == rid]


def _wait(predicate: Callable[[], bool], timeout_s: float = WAIT_S) -> bool:
    """Whether `predicate()` held within `timeout_s` (polled every 10 ms)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()
