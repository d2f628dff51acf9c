"""What securing a fleet costs: mTLS with the generated access-control list against open TCP.

1. Leader state -> follower command, 10 robots at 20 Hz: one host router on loopback (a
   `phalanx host` daemon's configuration: in mTLS mode its certificate and the access-control
   list `phalanx.hosts.access` generates for a 10-robot deployment), ten robot sessions
   (clients, each with its own `robot.<id>` certificate) and a world session. r1 publishes
   its state at 20 Hz; each of r2..r10 answers every leader state it receives with a
   command on its own `cmd` key; the world times each command from the leader state's
   publication (two hops through the router: leader -> follower -> world). The same
   process holds every session (Python callbacks share one interpreter in both modes).
2. Connecting a host: the time `zenoh.open` takes for a router (another host's daemon)
   joining this router, TLS handshake with certificates included.

    .venv/bin/python bench/bench_security.py                 # 60 s per mode, 20 connects
    .venv/bin/python bench/bench_security.py --seconds 20 --connects 10
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from calibration import Calibration

from phalanx.hosts import pki
from phalanx.hosts.access import host_acl
from phalanx.hosts.deployment import Deployment
from phalanx.wire.security import TlsFiles
from phalanx.wire.transport import FleetSession, TransportConfig, free_tcp_port

ROBOTS = [f"r{i}" for i in range(1, 11)]
FLEET = "bench"


def _deployment() -> Deployment:
    return Deployment.model_validate(
        {
            "name": FLEET, "fleet": FLEET, "scenario": "x.toml",
            "hosts": [
                {"name": "h1", "address": "127.0.0.1"}, {"name": "h2", "address": "127.0.0.2"}
            ],
            "robots": [{"id": r, "host": "h1"} for r in ROBOTS],
            "world": {"host": "h1"},
            "security": {"mode": "mtls", "operators": ["alice"]},
        }
    )  # fmt: skip


def _files(folder: Path, cn: str) -> TlsFiles:
    return TlsFiles(
        ca=str(folder / "ca.crt"), cert=str(folder / f"{cn}.crt"), key=str(folder / f"{cn}.key")
    )


def _configs(
    mode: str, folder: Path, port: int
) -> tuple[TransportConfig, dict[str, TransportConfig]]:
    scheme = "tls" if mode == "mtls" else "tcp"
    endpoint = f"{scheme}/127.0.0.1:{port}"
    secure = mode == "mtls"
    router = TransportConfig(
        mode="router", listen=(endpoint,),
        tls=_files(folder, "host.h1") if secure else None,
        acl=host_acl(_deployment(), "h1") if secure else None,
    )  # fmt: skip
    clients = {
        name: TransportConfig(
            mode="client", connect=(endpoint,), tls=_files(folder, cn) if secure else None
        )
        for name, cn in [*((r, f"robot.{r}") for r in ROBOTS), ("world", "world")]
    }
    return router, clients


def latency(mode: str, folder: Path, seconds: float) -> list[float]:
    """Leader state published -> follower command received by the world, seconds each."""
    router_cfg, client_cfgs = _configs(mode, folder, free_tcp_port())
    sent: dict[int, float] = {}
    got: list[float] = []
    lock = threading.Lock()
    with FleetSession(router_cfg) as router:
        sessions = {name: FleetSession(cfg) for name, cfg in client_cfgs.items()}
        try:
            world = sessions["world"]

            def on_cmd(sample: Any) -> None:
                seq = int(sample.payload.to_bytes().split(b":")[1])
                now = time.perf_counter()
                with lock:
                    if seq in sent:
                        got.append(now - sent[seq])

            world.hold(world.zenoh.declare_subscriber(f"phalanx/{FLEET}/robot/*/cmd", on_cmd))
            for rid in ROBOTS[1:]:
                _follower(sessions[rid], rid)
            time.sleep(1.0)
            leader = sessions["r1"].zenoh.declare_publisher(
                f"phalanx/{FLEET}/robot/r1/state", express=True
            )
            seq, period = 0, 1.0 / 20.0
            start = time.perf_counter()
            while time.perf_counter() - start < seconds:
                seq += 1
                with lock:
                    sent[seq] = time.perf_counter()
                leader.put(f"state:{seq}".encode())
                time.sleep(max(0.0, start + seq * period - time.perf_counter()))
            time.sleep(0.5)
            leader.undeclare()
        finally:
            for session in sessions.values():
                session.close()
        del router
    return got[len(ROBOTS) * 20 :]  # the first second left out


def _follower(session: FleetSession, rid: str) -> None:
    key = f"phalanx/{FLEET}/robot/{rid}/cmd"
    publisher = session.hold(session.zenoh.declare_publisher(key, express=True))

    def on_state(sample: Any) -> None:
        publisher.put(b"cmd:" + sample.payload.to_bytes().split(b":")[1])

    session.hold(session.zenoh.declare_subscriber(f"phalanx/{FLEET}/robot/r1/state", on_state))


def connect_times(mode: str, folder: Path, repeats: int, *, host: bool) -> list[float]:
    """Seconds for another host's router (`host`) or a robot's process to open its session
    to this host's router.
    """
    router_cfg, clients = _configs(mode, folder, free_tcp_port())
    endpoint = router_cfg.listen[0]
    secure = mode == "mtls"
    other = TransportConfig(
        mode="router", connect=(endpoint,), tls=_files(folder, "host.h2") if secure else None,
        acl=host_acl(_deployment(), "h2") if secure else None, open_timeout_s=5.0,
    ) if host else clients["r1"]  # fmt: skip
    times = []
    with FleetSession(router_cfg):
        for _ in range(repeats):
            start = time.perf_counter()
            session = FleetSession(other)
            times.append(time.perf_counter() - start)
            session.close()
    return times


def _pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--connects", type=int, default=20)
    args = parser.parse_args()
    cal = Calibration.measure()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        pki.init_ca(folder, fleet=FLEET)
        for cn in ["host.h1", "host.h2", "world", *(f"robot.{r}" for r in ROBOTS)]:
            pki.issue(folder, cn)
        print("| mode | samples | p50 | p99 | max | a host joins (median, max) | a process |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for mode in ("open", "mtls"):
            lat = latency(mode, folder, args.seconds)
            hosts = connect_times(mode, folder, args.connects, host=True)
            procs = connect_times(mode, folder, args.connects, host=False)
            print(
                f"| {mode} | {len(lat)} | {_pct(lat, 0.5) * 1e3:.2f} ms | "
                f"{_pct(lat, 0.99) * 1e3:.2f} ms | {max(lat) * 1e3:.2f} ms | "
                f"{statistics.median(hosts) * 1e3:.0f}, {max(hosts) * 1e3:.0f} ms | "
                f"{statistics.median(procs) * 1e3:.1f} ms |"
            )
            print(f"  ({mode}: p50 {cal.cal(_pct(lat, 0.5))}, p99 {cal.cal(_pct(lat, 0.99))})")


if __name__ == "__main__":
    main()
