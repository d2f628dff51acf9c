"""What a polled subscription costs its process per message: Zenoh's own RingChannel (no
Python per message, but what it drops is counted nowhere) against phalanx's counting
ring (`FleetSession.subscribe_polled`: a Zenoh callback appends the payload to a bounded
deque and counts what falls out). A second process publishes `--n` payloads at about 10 000
a second; the receiving process's CPU time per message is printed for each, with how many
it kept and counted as dropped, and as a ratio to the calibration workload timed in the
same run (`bench/calibration.py`).

    .venv/bin/python bench/bench_rings.py [--n 20000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import time

from calibration import Calibration

from phalanx.wire.transport import TransportConfig, free_tcp_port, open_session

PAYLOAD = b"\x07\x01" + bytes(100)


def publish(endpoint: str, key: str, n: int) -> None:
    """The publishing side (run as a separate process)."""
    with open_session(TransportConfig(mode="peer", connect=(endpoint,))) as session:
        publisher = session.zenoh.declare_publisher(key)
        time.sleep(1.0)
        for i in range(n):
            publisher.put(PAYLOAD)
            if i % 100 == 99:
                time.sleep(0.01)
        time.sleep(0.5)
        publisher.undeclare()


def _cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def measure(kind: str, endpoint: str, session: object, n: int) -> tuple[float, int, int]:
    """CPU µs per message in this process, messages kept, messages counted dropped."""
    import zenoh

    from phalanx.wire.messages import RobotFlags

    key = f"bench/{kind}/{time.monotonic_ns()}"
    if kind == "zenoh-ring":
        sub = session.zenoh.declare_subscriber(key, zenoh.handlers.RingChannel(24))  # type: ignore[attr-defined]
    else:
        ring = session.subscribe_polled(key, RobotFlags, 24)  # type: ignore[attr-defined]
    before = _cpu_s()
    subprocess.run([sys.executable, __file__, "--publish", endpoint, key, str(n)], check=True)
    cpu_us = 1e6 * (_cpu_s() - before) / n
    if kind == "zenoh-ring":
        kept = 0
        while sub.try_recv() is not None:
            kept += 1
        sub.undeclare()
        return cpu_us, kept, 0
    stats = session.stats  # type: ignore[attr-defined]
    dropped = stats.ring_dropped["RobotFlags"]
    kept = ring.drain(lambda _k, _m: None)
    stats.ring_dropped.clear()
    return cpu_us, kept, dropped


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=20_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--publish", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.publish:
        publish(args.publish[0], args.publish[1], int(args.publish[2]))
        return
    cal = Calibration.measure()
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    print("| ring | run | receiver CPU per message (micro-cal) | kept | counted dropped |")
    print("|---|---:|---:|---:|---:|")
    with open_session(TransportConfig(mode="peer", listen=(endpoint,))) as session:
        for run in range(args.repeats):
            for kind in ("zenoh-ring", "counting-ring"):
                cpu_us, kept, dropped = measure(kind, endpoint, session, args.n)
                ucal = 1e6 * cal.ratio(cpu_us * 1e-6)
                print(
                    f"| {kind} | {run} | {cpu_us:.2f} µs ({ucal:.0f}) | {kept} | {dropped} |",
                    flush=True,
                )
    Calibration.measure()


if __name__ == "__main__":
    main()
