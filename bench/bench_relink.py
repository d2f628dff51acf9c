"""A router frozen past the Zenoh lease, again and again: how often a client is left deaf,
and how soon `Relinker` brings it back (docs/RELIABILITY.md).

A router process publishes a message every 50 ms, as a world sends its frames; three
client sessions (phalanx's `FleetSession`, as agents hold) hear it. Each cycle freezes the
router (SIGSTOP) for `--freeze` seconds, resumes it, and waits `--settle` seconds: a
client that has heard nothing since is deaf. With `--relink on` every client has a
`Relinker` watching what it hears (the agents' own, at its default 5 s); the cycle then
also records how long after the resume every client heard again.

    .venv/bin/python bench/bench_relink.py                           # both transports, both ways
    .venv/bin/python bench/bench_relink.py --transport lowlatency --relink off --cycles 40

The figures are counts and a time set by the relink's own wait, not by the CPU: no
calibration workload.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager

from phalanx.wire.messages import AgentEvent
from phalanx.wire.relink import Relinker
from phalanx.wire.transport import (
    FleetSession,
    TransportConfig,
    free_tcp_port,
    loopback_endpoint,
    open_session,
)

KEY = "phalanx/bench/robots/w/event"
CLIENTS = 3
PERIOD_S = 0.05
ROUTER = """
import sys, time
from phalanx.wire.messages import AgentEvent
from phalanx.wire.transport import TransportConfig, open_session
cfg = TransportConfig.model_validate_json(sys.argv[1])
with open_session(cfg) as session:
    k = 0
    while True:
        event = AgentEvent(robot_id="w", t_s=k * 0.05, source="HOLD", target="NAVIGATE",
                           reason="tick")
        session.publish(sys.argv[2], event)
        if k == 0:
            print("up", flush=True)
        k += 1
        time.sleep(0.05)
"""


class Ear:
    """When a client last heard the router (monotonic), set on Zenoh's thread."""

    def __init__(self) -> None:
        self.heard_s: float | None = None
        self.lock = threading.Lock()

    def __call__(self, _key: str, _event: AgentEvent) -> None:
        with self.lock:
            self.heard_s = time.monotonic()

    def since(self, t_s: float) -> bool:
        """Whether it heard anything after `t_s`."""
        with self.lock:
            return self.heard_s is not None and self.heard_s > t_s


@contextmanager
def _router(cfg: TransportConfig) -> Iterator[subprocess.Popen[bytes]]:
    argv = [sys.executable, "-c", ROUTER, cfg.model_dump_json(), KEY]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE)
    try:
        if proc.stdout is None or not proc.stdout.readline():
            raise RuntimeError("the router process did not start")
        yield proc
    finally:
        os.kill(proc.pid, signal.SIGCONT)
        proc.kill()
        proc.wait(10)


def run(lowlatency: bool, relink: bool, cycles: int, freeze_s: float, settle_s: float) -> str:
    """One configuration's line of the table."""
    endpoint = loopback_endpoint(free_tcp_port())
    router = TransportConfig(mode="router", listen=(endpoint,), lowlatency=lowlatency)
    client = TransportConfig(mode="client", connect=(endpoint,), lowlatency=lowlatency)
    deaf_cycles, deaf_clients, back_s = 0, 0, []
    with _router(router) as proc, ExitStack() as stack:
        ears, sessions = [], []
        for _ in range(CLIENTS):
            session: FleetSession = stack.enter_context(open_session(client))
            ear = Ear()
            session.subscribe(KEY, AgentEvent, ear)
            if relink:
                watch = stack.enter_context(Relinker(session, lambda ear=ear: ear.heard_s))
                watch.start()
            ears.append(ear)
            sessions.append(session)
        time.sleep(1.0)
        for _ in range(cycles):
            os.kill(proc.pid, signal.SIGSTOP)
            time.sleep(freeze_s)
            os.kill(proc.pid, signal.SIGCONT)
            resumed = time.monotonic()
            deadline = resumed + settle_s
            while time.monotonic() < deadline and not all(e.since(resumed) for e in ears):
                time.sleep(0.01)
            deaf = sum(not e.since(resumed) for e in ears)
            deaf_clients += deaf
            deaf_cycles += deaf > 0
            if deaf == 0:
                back_s.append(time.monotonic() - resumed)
        relinks = sum(s.relinks for s in sessions)
    back = f"{statistics.median(back_s):5.2f} / {max(back_s):5.2f}" if back_s else "      -      "
    transport = "lowlatency" if lowlatency else "default"
    return (
        f"{transport:>10} {'on' if relink else 'off':>6} {cycles:>6} {deaf_cycles:>10} "
        f"{deaf_clients:>12} {relinks:>7}   {back}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--transport", nargs="+", default=["lowlatency", "default"],
                        choices=["lowlatency", "default"])  # fmt: skip
    parser.add_argument("--relink", nargs="+", default=["off", "on"], choices=["off", "on"])
    parser.add_argument("--cycles", type=int, default=20)
    parser.add_argument("--freeze", type=float, default=2.0, help="s the router is stopped")
    parser.add_argument(
        "--settle", type=float, default=10.0, help="s after the resume a client may take"
    )
    args = parser.parse_args()
    logging.getLogger("phalanx.transport").setLevel(logging.ERROR)  # each relink warns
    print(f"router frozen {args.freeze:g} s per cycle, {CLIENTS} clients, deaf = nothing heard "
          f"within {args.settle:g} s of the resume")  # fmt: skip
    print(f"{'transport':>10} {'relink':>6} {'cycles':>6} {'deaf_cycles':>10} "
          f"{'deaf_clients':>12} {'relinks':>7}   all_back_s p50 / max")  # fmt: skip
    for transport in args.transport:
        for relink in args.relink:
            line = run(transport == "lowlatency", relink == "on", args.cycles, args.freeze,
                       args.settle)  # fmt: skip
            print(line, flush=True)


if __name__ == "__main__":
    main()
