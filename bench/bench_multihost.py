"""A fleet across three hosts in network namespaces: launch time, leader-state latency,
lost-link detection and rejoin. Needs root and iproute2 (`ip netns`).

Hosts: `world` (the world and the launcher, as a laptop), `robot-a` (r1), `robot-b` (r2,
r3), each running `phalanx host` in its own namespace (IPv4 only) on one bridge. Times are
read from CLOCK_MONOTONIC, which every namespace of the machine shares.

- launch: `phalanx launch` started -> every robot's state seen (daemons already up, as
  systemd units would be); the launcher's own phases are printed too.
- latency: a leader probe on robot-a publishes RobotState at 20 Hz stamped with
  CLOCK_MONOTONIC; follower probes on robot-b (other host) and on robot-a (same host)
  decode it: latency = decoded - stamped. Path across hosts: client -> robot-a's daemon
  -> robot-b's daemon -> client (and via a `phalanx router` hub in the router topology).
  Measured with the daemons idle and with the paper fleet running.
- link: robot-b's cable pulled for 3 s and plugged back, repeatedly, with the fleet
  running in real time: when the world notices (r2/r3's liveliness gone: it commands
  them zero from then on), when their bodies are at rest (P3DX deceleration 0.3 m/s^2),
  when the world sees them again, and when they drive again.

    .venv/bin/python bench/bench_multihost.py [--repeats 3] [--latency-s 20] [--trials 3]
"""

from __future__ import annotations

import argparse
import json
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from calibration import Calibration

from phalanx.core.config_files import CONFIG_ROOT

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "lab"))
import netlab
from netlab import NetLab, unavailable

HOSTS = ("world", "robot-a", "robot-b")
PLACEMENT = {"r1": "robot-a", "r2": "robot-b", "r3": "robot-b"}
WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
CLI = [sys.executable, "-m", "phalanx"]
PORT = 7447
RATE_HZ = 20.0
WARMUP_S = 1.0


# --- fleet plumbing -----------------------------------------------------------------------


def write_deployment(lab: NetLab, folder: Path, name: str, *, lease_ms: int, router: bool) -> Path:
    lines = [f'name = "{name}"', f'fleet = "{name}"', f'scenario = "{WEDGE}"', 'clock = "realtime"']
    lines += ["[security]", 'mode = "open"']  # the links' own costs (bench_security: TLS)
    lines += ["[zenoh]", f"lease_ms = {lease_ms}", "retry_max_ms = 500"]
    if router:
        lines.append(f'router = {{ address = "{lab.address("world")}", port = 7448 }}')
    lines += ["[world]", 'host = "world"', f'out_dir = "{folder / "results"}"', "recording = false"]
    for host in HOSTS:
        lines += ["[[hosts]]", f'name = "{host}"', f'address = "{lab.address(host)}"']
    for rid, host in PLACEMENT.items():
        lines += ["[[robots]]", f'id = "{rid}"', f'host = "{host}"']
    path = folder / f"{name}.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


class Daemons:
    """`phalanx host` in every namespace (and `phalanx router` for the hub topology)."""

    def __init__(self, lab: NetLab, deployment: Path, logs: Path, *, router: bool) -> None:
        self.procs: list[subprocess.Popen[bytes]] = []
        logs.mkdir(parents=True, exist_ok=True)
        if router:
            self._start(lab, "world", [*CLI, "router", str(deployment)], logs / "router.log")
        for host in HOSTS:
            argv = [*CLI, "host", str(deployment), "--name", host, "--quiet"]
            self._start(lab, host, argv, logs / f"host-{host}.log")

    def _start(self, lab: NetLab, host: str, argv: list[str], log: Path) -> None:
        with log.open("wb") as sink:
            self.procs.append(lab.popen(host, argv, stdout=sink, stderr=subprocess.STDOUT))

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in self.procs:
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)


class Observer:
    """`python netlab.py observe` in a namespace, its records as they come."""

    def __init__(self, lab: NetLab, host: str, fleet: str) -> None:
        argv = [sys.executable, netlab.__file__, "observe", "--fleet", fleet]
        argv += ["--connect", f"tcp/127.0.0.1:{PORT}", "--seconds", "900"]
        self.proc = lab.popen(host, argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        self.records: list[dict[str, Any]] = []
        self.lock = threading.Lock()
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        for raw in self.proc.stdout or ():
            with self.lock:
                self.records.append(json.loads(raw))

    def first(
        self, predicate: Callable[[list[dict[str, Any]]], bool], timeout_s: float
    ) -> float | None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.lock:
                records = list(self.records)
            if predicate(records):
                return time.monotonic()
            time.sleep(0.005)
        return None

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            self.proc.wait(10)
        self.reader.join(2)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


def seen(
    records: list[dict[str, Any]],
    robots: tuple[str, ...],
    after: float,
    test: Callable[[dict[str, Any]], bool],
) -> bool:
    return all(
        any(r.get("robot") == rid and r["t"] > after and test(r) for r in records) for rid in robots
    )


def run_cli(
    lab: NetLab, host: str, args: list[str], timeout_s: float = 90.0
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        lab.command(host, [*CLI, *args]),
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
    )


# --- launch time --------------------------------------------------------------------------


def bench_launch(lab: NetLab, folder: Path, repeats: int) -> list[dict[str, float]]:
    deployment = write_deployment(lab, folder, "blaunch", lease_ms=1000, router=False)
    daemons = Daemons(lab, deployment, folder / "logs-launch", router=False)
    try:
        return [_launch_once(lab, deployment, k) for k in range(repeats)]
    finally:
        daemons.close()


def _launch_once(lab: NetLab, deployment: Path, k: int) -> dict[str, float]:
    observer = Observer(lab, "world", "blaunch")
    observer.first(lambda rs: any(r["kind"] == "ready" for r in rs), 30.0)
    started = time.monotonic()
    launched = run_cli(
        lab,
        "world",
        ["launch", str(deployment), "--detach", "--no-table", "--no-logs", "--run-id", f"l{k}"],
    )
    up = observer.first(
        lambda rs: seen(rs, tuple(PLACEMENT), started, lambda r: r["kind"] == "state"), 30.0
    )
    observer.close()
    stop_started = time.monotonic()
    stopped = run_cli(lab, "world", ["stop", str(deployment)])
    stop_s = time.monotonic() - stop_started
    if launched.returncode != 0 or up is None or stopped.returncode != 0:
        raise RuntimeError(launched.stdout + launched.stderr + stopped.stdout + stopped.stderr)
    return {
        "run": k,
        "first_state_s": up - started,
        "hosts_s": _phase(launched.stdout, r"hosts present: .* \(([\d.]+) s\)"),
        "spawned_s": _phase(launched.stdout, r"run \S+ started \(([\d.]+) s\)"),
        "up_s": _phase(launched.stdout, r"fleet up in ([\d.]+) s"),
        "stop_s": stop_s,
    }


def _phase(text: str, pattern: str) -> float:
    match = re.search(pattern, text)
    return float(match.group(1)) if match else float("nan")


# --- leader-state latency -----------------------------------------------------------------


def probe_pub(connect: str, seconds: float) -> None:
    from phalanx.wire.keys import robot_key
    from phalanx.wire.messages import RobotState
    from phalanx.wire.transport import TransportConfig, open_session

    with open_session(TransportConfig(mode="client", connect=(connect,))) as session:
        time.sleep(1.0)  # the subscribers' interest reaches this side
        key = robot_key("probe", "lead", "state")
        next_at = time.monotonic()
        end = next_at + seconds
        seq = 0
        while (now := time.monotonic()) < end:
            seq += 1
            state = RobotState(
                robot_id="lead",
                seq=seq,
                stamp_s=now,
                x_m=0.0,
                y_m=0.0,
                theta_rad=0.0,
                v_mps=0.15,
                omega_radps=0.0,
                fsm_state="NAVIGATE",
            )
            session.publish(key, state)
            next_at += 1.0 / RATE_HZ
            time.sleep(max(0.0, next_at - time.monotonic()))


def probe_sub(connect: str, seconds: float) -> None:
    from phalanx.wire.keys import robot_key
    from phalanx.wire.messages import RobotState
    from phalanx.wire.transport import TransportConfig, open_session

    latencies: list[tuple[float, float]] = []
    with open_session(TransportConfig(mode="client", connect=(connect,))) as session:
        session.subscribe(
            robot_key("probe", "lead", "state"),
            RobotState,
            lambda _k, s: latencies.append((time.monotonic(), time.monotonic() - s.stamp_s)),
        )
        sys.stdout.write("ready\n")
        sys.stdout.flush()
        time.sleep(seconds)
    start = latencies[0][0] if latencies else 0.0
    sys.stdout.write(json.dumps([lat for t, lat in latencies if t - start > WARMUP_S]) + "\n")


def measure_latency(lab: NetLab, seconds: float) -> dict[str, list[float]]:
    bench = str(Path(__file__).resolve())
    subs = {}
    for name, host in (("other host", "robot-b"), ("same host", "robot-a")):
        argv = [
            sys.executable,
            bench,
            "_sub",
            "--connect",
            f"tcp/127.0.0.1:{PORT}",
            "--seconds",
            str(seconds + 3.0),
        ]
        subs[name] = lab.popen(
            host, argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
        )
    for proc in subs.values():
        if proc.stdout is not None:
            proc.stdout.readline()  # ready
    pub = lab.popen(
        "robot-a",
        [
            sys.executable,
            bench,
            "_pub",
            "--connect",
            f"tcp/127.0.0.1:{PORT}",
            "--seconds",
            str(seconds),
        ],
    )
    pub.wait(seconds + 30)
    out = {}
    for name, proc in subs.items():
        text, _ = proc.communicate(timeout=seconds + 30)
        out[name] = json.loads(text.strip().splitlines()[-1])
    return out


def bench_latency(lab: NetLab, folder: Path, seconds: float) -> list[dict[str, Any]]:
    rows = []
    for topology in ("mesh", "router"):
        deployment = write_deployment(
            lab, folder, f"blat{topology}", lease_ms=1000, router=topology == "router"
        )
        daemons = Daemons(
            lab, deployment, folder / f"logs-lat-{topology}", router=topology == "router"
        )
        try:
            time.sleep(3.0)  # daemons up and linked
            for load in ("idle", "fleet running"):
                launcher = None
                if load == "fleet running":
                    launcher = lab.popen(
                        "world",
                        [
                            *CLI,
                            "launch",
                            str(deployment),
                            "--no-table",
                            "--no-logs",
                            "--set",
                            "duration_s=200",
                            "--run-id",
                            "lat",
                        ],
                        stdout=subprocess.DEVNULL,
                        stderr=subprocess.DEVNULL,
                    )
                    time.sleep(8.0)
                for path, samples in measure_latency(lab, seconds).items():
                    rows.append(
                        {"topology": topology, "load": load, "path": path, **_quantiles(samples)}
                    )
                if launcher is not None:
                    launcher.send_signal(signal.SIGINT)
                    launcher.wait(60)
        finally:
            daemons.close()
    return rows


def _quantiles(samples: list[float]) -> dict[str, Any]:
    if not samples:
        return {"n": 0}
    ordered = sorted(samples)

    def pick(q: float) -> float:
        return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]

    return {
        "n": len(ordered),
        "p50_ms": pick(0.5) * 1e3,
        "p90_ms": pick(0.9) * 1e3,
        "p99_ms": pick(0.99) * 1e3,
        "max_ms": ordered[-1] * 1e3,
    }


# --- lost link ----------------------------------------------------------------------------


def bench_link(lab: NetLab, folder: Path, trials: int, lease_ms: int) -> list[dict[str, Any]]:
    name = f"blink{lease_ms}"
    deployment = write_deployment(lab, folder, name, lease_ms=lease_ms, router=False)
    daemons = Daemons(lab, deployment, folder / f"logs-link-{lease_ms}", router=False)
    near = launcher = None
    try:
        near = Observer(lab, "world", name)
        launcher = lab.popen(
            "world",
            [*CLI, "launch", str(deployment), "--no-table", "--no-logs", "--set",
             "duration_s=600", "--run-id", "link", "--host-wait", "60"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        if near.first(lambda rs: _moving(rs, 0.0), 60.0) is None:
            raise RuntimeError("the fleet never moved")
        time.sleep(3.0)
        return [_link_trial(lab, near, lease_ms, k) for k in range(trials)]
    finally:
        if launcher is not None and launcher.poll() is None:
            launcher.send_signal(signal.SIGINT)
            launcher.wait(60)
        if near is not None:
            near.close()
        daemons.close()


FAR = ("r2", "r3")


def _moving(records: list[dict[str, Any]], after: float) -> bool:
    return seen(records, FAR, after, lambda r: r["kind"] == "sense" and r["v"] > 0.05)


def _link_trial(lab: NetLab, near: Observer, lease_ms: int, trial: int) -> dict[str, Any]:
    pulled = time.monotonic()
    lab.set_link("robot-b", up=False)
    noticed = near.first(
        lambda rs: seen(rs, FAR, pulled, lambda r: r["kind"] == "alive" and not r["alive"]), 10.0
    )
    rest = near.first(
        lambda rs: seen(rs, FAR, pulled, lambda r: r["kind"] == "sense" and abs(r["v"]) < 0.005),
        10.0,
    )
    time.sleep(max(0.0, pulled + 3.0 - time.monotonic()))
    plugged = time.monotonic()
    lab.set_link("robot-b", up=True)
    back = near.first(
        lambda rs: seen(rs, FAR, plugged, lambda r: r["kind"] == "alive" and r["alive"]), 20.0
    )
    driving = near.first(
        lambda rs: _moving(rs, plugged) and seen(rs, FAR, plugged, lambda r: r["kind"] == "state"),
        20.0,
    )
    time.sleep(4.0)
    return {
        "lease_ms": lease_ms,
        "trial": trial,
        "noticed_s": _since(noticed, pulled),
        "at_rest_s": _since(rest, pulled),
        "rejoined_s": _since(back, plugged),
        "driving_s": _since(driving, plugged),
    }


def _since(at: float | None, start: float) -> float:
    return float("nan") if at is None else at - start


# --- report -------------------------------------------------------------------------------


def _table(rows: list[dict[str, Any]], columns: list[str]) -> None:
    print("| " + " | ".join(columns) + " |")
    print("|" + "---|" * len(columns))
    for row in rows:
        cells = [
            f"{row[c]:.2f}" if isinstance(row.get(c), float) else str(row.get(c, "-"))
            for c in columns
        ]
        print("| " + " | ".join(cells) + " |")
    print()


def main() -> None:
    Calibration.measure()  # (the unit every time below can be divided by, on any machine)
    parser = argparse.ArgumentParser()
    parser.add_argument(
        "command",
        nargs="?",
        default="all",
        choices=["all", "launch", "latency", "link", "_pub", "_sub"],
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--latency-s", type=float, default=20.0)
    parser.add_argument("--trials", type=int, default=3)
    parser.add_argument("--connect", default="")
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    if args.command == "_pub":
        probe_pub(args.connect, args.seconds)
        return
    if args.command == "_sub":
        probe_sub(args.connect, args.seconds)
        return
    reason = unavailable()
    if reason is not None:
        print(f"skipped: {reason}")
        return
    with NetLab(HOSTS) as lab, tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        if args.command in ("all", "launch"):
            rows = bench_launch(lab, folder, args.repeats)
            print("## Launch of a 3-host fleet (daemons already running)\n")
            _table(rows, ["run", "hosts_s", "spawned_s", "up_s", "first_state_s", "stop_s"])
            firsts = [r["first_state_s"] for r in rows]
            print(f"median launch -> every robot publishing: {statistics.median(firsts):.2f} s\n")
        if args.command in ("all", "latency"):
            rows = bench_latency(lab, folder, args.latency_s)
            print("## Leader state, published -> decoded, 20 Hz\n")
            _table(rows, ["topology", "load", "path", "n", "p50_ms", "p90_ms", "p99_ms", "max_ms"])
        if args.command in ("all", "link"):
            rows = [
                row for lease in (500, 1000) for row in bench_link(lab, folder, args.trials, lease)
            ]
            print("## robot-b's link pulled for 3 s, then plugged back (real time)\n")
            columns = ["lease_ms", "trial", "noticed_s", "at_rest_s", "rejoined_s", "driving_s"]
            _table(rows, columns)
            for lease in (500, 1000):
                mine = [r for r in rows if r["lease_ms"] == lease]
                medians = {c: statistics.median(r[c] for r in mine) for c in columns[2:]}
                print(
                    f"lease {lease} ms, medians: "
                    + ", ".join(f"{c} {v:.2f}" for c, v in medians.items())
                )


if __name__ == "__main__":
    main()
