"""Leader state published -> follower command computed, between processes over Zenoh.

Every robot is its own process (spawned, never forked: Zenoh runs threads). Each one
publishes its RobotState on its own 20 Hz timer with a random phase, as free-running
agents do; each follower subscribes to its own leader in a grid formation (rows chained
behind the root) and, on every state received, runs the real agent core's step and
publishes its command. Latency = command computed (follower) - state stamped (leader),
both read from CLOCK_MONOTONIC, one clock for every process on this machine. Beside
it, the hop alone (state received - state stamped): the rest is the follower's step,
and `step_ms` the step's share of the tail, p99 - hop p99. Two sonar readings, each
robot's the same every step: open space (every transducer at its maximum range: nothing
to mask, the benchmark's reading by default), and the formation's own robots as the
simulated world's ring hears them with every robot in its slot (`--sonar formation`:
masking them out is then part of every step). Each robot's loop runs with what exists
before it frozen for the garbage collector, as an agent process's does
(`phalanx.runtime.heap.lifelong_heap`); `--heap plain` leaves it as it is.

Two topologies: every process a Zenoh client of one router (as `phalanx up` runs), and
peers connected directly (each listens on its own endpoint and connects to the others).
Scouting is off in both. Two transports: Zenoh's default, and its low-latency one (a put
written to the link from the calling thread), which `phalanx up` runs its processes on
(`--lowlatency`). Two links: TCP on loopback, and Unix-domain sockets in a directory
only this user can open, which `phalanx up` runs on (`--link unixsock`); with both, a
last table gives each row's Unix-socket figures over the same row's on TCP. A row whose
robots do not all start within READY_S, or do not all report, is printed as failed (each
robot's error on stderr), its processes killed, and the benchmark goes on.

    .venv/bin/python bench/bench_zenoh_latency.py [--robots 3 10 30] [--seconds 10]
        [--topology router peer] [--transport default lowlatency] [--link tcp unixsock]
        [--sonar open formation] [--heap frozen plain]
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import multiprocessing as mp
import queue
import random
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any, NamedTuple

from calibration import Calibration, load

from phalanx.agents.agent import Agent, Observation
from phalanx.core.config import Scenario
from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_robot, load_scenario
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import Pose2D, Twist2D, Vec2
from phalanx.core.quantities import MAX_DURATION_S
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.core.scenarios import grid_scenario
from phalanx.runtime.batch import BatchRunner
from phalanx.runtime.heap import lifelong_heap
from phalanx.wire.keys import robot_key
from phalanx.wire.messages import RobotState, VelocityCommand
from phalanx.wire.transport import (
    TransportConfig,
    free_tcp_port,
    loopback_endpoint,
    open_session,
    unix_socket_endpoint,
)

RATE_HZ = 20.0
WARMUP_S = 1.0  # connection set-up and first-call costs are not steady state
READY_S = 60.0  # every robot's session open and subscribed, or the row fails
FLEET = "bench"


class RowFailed(RuntimeError):
    """A row's fleet did not run: some robots never started or never reported."""


def fleet_scenario(n: int) -> Scenario:
    """The paper scenario's grid of `n` robots, no leader timed out in a benchmark's run
    (the longest timeout a scenario may have: a day).
    """
    base = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
    return apply_overrides(grid_scenario(base, n), [f"leader_timeout_s={MAX_DURATION_S}"])


def driving(rid: str, at: Vec2, seq: int = 0, stamp_s: float = 0.0) -> RobotState:
    """`rid`'s state at `at`, heading along x at 0.15 m/s, as every robot here sends it."""
    return RobotState(
        robot_id=rid,
        seq=seq,
        stamp_s=stamp_s,
        x_m=at.x_m,
        y_m=at.y_m,
        theta_rad=0.0,
        v_mps=0.15,
        omega_radps=0.0,
        fsm_state="NAVIGATE",
    )


def sonar_ranges(n: int, sonar: str) -> dict[str, tuple[float, ...]]:
    """Every robot's sonar ranges (m) in the `n`-robot grid, read the same every step:
    `open` space (every transducer at its maximum range), or the `formation`'s own
    robots as the simulated world's ring hears them with every robot in its slot.
    """
    scenario = fleet_scenario(n)
    if sonar == "open":
        ring = load_robot("p3dx").sonar
        ranges = (ring.max_range_m,) * len(ring.units)
        return dict.fromkeys(scenario_formation(scenario).robot_ids, ranges)
    runner = BatchRunner(scenario)
    statuses, _ = runner.world.statuses()
    return {rid: s.sonar_ranges_m for rid, s in zip(runner.agents, statuses, strict=True)}


def robot(
    cfg: TransportConfig,
    rid: str,
    n: int,
    seconds: float,
    ranges: tuple[float, ...],
    sync: tuple[Any, Any],
    frozen: bool = True,
) -> None:
    """One robot: publish own state at RATE_HZ, step on every leader state received (its
    sonar reading `ranges`); `sync`: the fleet's start barrier and the results' queue;
    `frozen`: its loop runs with what exists before it frozen, as an agent process's
    does (`lifelong_heap`).
    """
    ready, out = sync
    scenario = fleet_scenario(n)
    formation = scenario_formation(scenario)
    agent = Agent(rid, scenario=scenario, robot=load_robot("p3dx"), formation=formation)
    leader_id = formation.leader_of(rid)
    here = formation.positions[rid]
    inbox: queue.SimpleQueue[RobotState] = queue.SimpleQueue()
    latencies: list[tuple[float, float]] = []  # (state -> command, state -> received)
    state = driving(rid, here)
    status = RobotStatus(sonar_ranges_m=ranges)
    with open_session(cfg) as session:
        if leader_id is not None:
            session.subscribe(
                robot_key(FLEET, leader_id, "state"), RobotState, lambda _k, m: inbox.put(m)
            )
        ready.wait(timeout=READY_S)  # a robot that cannot start breaks it for all
        start = time.monotonic()
        next_pub = start + random.random() / RATE_HZ
        end = start + WARMUP_S + seconds
        seq = 0
        with lifelong_heap() if frozen else contextlib.nullcontext():
            while (now := time.monotonic()) < end:
                if now >= next_pub:
                    seq += 1
                    state = state.model_copy(update={"seq": seq, "stamp_s": now})
                    session.publish(robot_key(FLEET, rid, "state"), state)
                    next_pub += 1.0 / RATE_HZ
                    continue
                try:
                    lead = inbox.get(timeout=max(0.0, next_pub - time.monotonic()))
                except queue.Empty:
                    continue
                got = time.monotonic()
                odo = Odometry(Pose2D(here.x_m, here.y_m, 0.0), Twist2D(0.15, 0.0), got)
                result = agent.step(Observation(odo, status), {lead.robot_id: lead.peer()}, got)
                done = time.monotonic()
                session.publish(
                    robot_key(FLEET, rid, "cmd"),
                    VelocityCommand(
                        robot_id=rid,
                        tick=seq,
                        stamp_s=done,
                        v_mps=result.command.v_mps,
                        omega_radps=result.command.omega_radps,
                    ),
                )
                if got - start > WARMUP_S:
                    latencies.append((done - lead.stamp_s, got - lead.stamp_s))
    out.put(latencies)


def _endpoint(folder: Path | None, name: str) -> str:
    """A TCP loopback endpoint (no folder), or a Unix-domain socket `name` in `folder`."""
    if folder is None:
        return loopback_endpoint(free_tcp_port())
    return unix_socket_endpoint(folder / f"{name}.sock")


def _configs(
    n: int, topology: str, lowlatency: bool, folder: Path | None
) -> tuple[TransportConfig | None, list[TransportConfig]]:
    if topology == "router":
        endpoint = _endpoint(folder, "router")
        client = TransportConfig(mode="client", connect=(endpoint,), lowlatency=lowlatency)
        router = TransportConfig(mode="router", listen=(endpoint,), lowlatency=lowlatency)
        return router, [client] * n
    eps = [_endpoint(folder, f"g{i}") for i in range(n)]
    # Peer i connects to every earlier peer: a full mesh with one link per pair.
    return None, [
        TransportConfig(
            mode="peer", listen=(eps[i],), connect=tuple(eps[:i]), lowlatency=lowlatency
        )
        for i in range(n)
    ]


def measure(
    n: int,
    seconds: float,
    topology: str,
    lowlatency: bool = False,
    link: str = "tcp",
    sonar: str = "open",
    heap: str = "frozen",
) -> list[tuple[float, float]]:
    """Every follower command's latency and its hop's (s), in an `n`-robot fleet; `link`
    tcp (loopback) or unixsock (sockets in a new directory of mode 0700); `sonar`: see
    `sonar_ranges`; `heap`: frozen for each robot's loop (as an agent process runs) or
    plain (`robot`).
    """
    with tempfile.TemporaryDirectory(prefix="phalanx-bench-") as folder:  # (mode 0700)
        here = Path(folder) if link == "unixsock" else None
        configs = _configs(n, topology, lowlatency, here)
        return _measure(n, seconds, configs, sonar_ranges(n, sonar), frozen=heap == "frozen")


def _measure(
    n: int,
    seconds: float,
    configs: tuple[TransportConfig | None, list[TransportConfig]],
    ranges: dict[str, tuple[float, ...]],
    *,
    frozen: bool = True,
) -> list[tuple[float, float]]:
    router_cfg, cfgs = configs
    ctx = mp.get_context("spawn")
    ready = ctx.Barrier(n)
    out = ctx.Queue()
    router = open_session(router_cfg) if router_cfg else None
    procs = [
        ctx.Process(
            target=robot,
            args=(cfgs[i], f"g{i}", n, seconds, ranges[f"g{i}"], (ready, out), frozen),
            daemon=True,
        )
        for i in range(n)
    ]
    try:
        for p in procs:
            p.start()
        results: list[list[tuple[float, float]]] = []
        give_up = time.monotonic() + READY_S + seconds + 60.0
        while len(results) < n:
            try:
                results.append(out.get(timeout=max(0.1, give_up - time.monotonic())))
            except queue.Empty:
                raise RowFailed(f"{n - len(results)} of {n} robots sent no figures") from None
        deadline = time.monotonic() + 30.0
        for p in procs:
            p.join(max(0.1, deadline - time.monotonic()))
    finally:
        for p in procs:  # its figures are in (or the row failed): one still here is killed
            if p.is_alive():
                p.kill()
                p.join(5)
        if router is not None:
            router.close()
    return [x for r in results for x in r]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--robots", type=int, nargs="+", default=[3, 10, 30])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument(
        "--topology", nargs="+", default=["router", "peer"], choices=["router", "peer"]
    )
    parser.add_argument(
        "--transport", nargs="+", default=["default"], choices=["default", "lowlatency"]
    )
    parser.add_argument("--link", nargs="+", default=["tcp"], choices=["tcp", "unixsock"])
    parser.add_argument("--sonar", nargs="+", default=["open"], choices=["open", "formation"])
    parser.add_argument("--heap", nargs="+", default=["frozen"], choices=["frozen", "plain"])
    args = parser.parse_args()
    cal = Calibration.measure()
    print(f"leader state -> follower command over Zenoh, {RATE_HZ:.0f} Hz per robot, one host")
    print(
        "sonar      heap    link      topology  transport   robots  samples  p50_ms  p90_ms  p99_ms"
        "  max_ms  p99_mcal  hop_p50_ms  hop_p99_ms  step_ms  load"
    )
    rows: dict[Row, tuple[float, float]] = {}
    for sonar, heap in itertools.product(args.sonar, args.heap):
        for transport in args.transport:
            for topology in args.topology:
                for n in args.robots:
                    for link in args.link:
                        row = Row(link, topology, transport, n, sonar, heap)
                        figures = _row(row, args.seconds, cal)
                        if figures is not None:
                            rows[row] = figures
    Calibration.measure()
    _ratios(rows)


class Row(NamedTuple):
    """One row of the table: what was measured."""

    link: str
    topology: str
    transport: str
    robots: int
    sonar: str = "open"
    heap: str = "frozen"


def _row(row: Row, seconds: float, cal: Calibration) -> tuple[float, float] | None:
    """Measure and print `row`; its p50 and p99 (s), None if it failed."""
    name = (
        f"{row.sonar:9s}  {row.heap:6s}  {row.link:8s}  {row.topology:8s}  "
        f"{row.transport:10s}  {row.robots:6d}"
    )
    try:
        lowlatency = row.transport == "lowlatency"
        pairs = measure(
            row.robots, seconds, row.topology, lowlatency, row.link, row.sonar, row.heap
        )
    except RowFailed as failed:  # (each robot's own error is on stderr)
        print(f"{name}  failed: {failed}", flush=True)
        return None
    lat = sorted(total for total, _ in pairs)
    q = statistics.quantiles(lat, n=100)
    hop = statistics.quantiles([h for _, h in pairs], n=100)
    print(
        f"{name}  {len(lat):7d}  {1e3 * q[49]:6.3f}  "
        f"{1e3 * q[89]:6.3f}  {1e3 * q[98]:6.3f}  {1e3 * lat[-1]:6.3f}  "
        f"{1e3 * cal.ratio(q[98]):8.1f}  {1e3 * hop[49]:10.3f}  {1e3 * hop[98]:10.3f}  "
        f"{1e3 * (q[98] - hop[98]):7.3f}  {load()}",
        flush=True,
    )
    return q[49], q[98]


def _ratios(rows: dict[Row, tuple[float, float]]) -> None:
    """Each row's p50 and p99 on Unix-domain sockets over the same row's on TCP, where
    both ran.
    """
    pairs = [
        (row, figures, rows[row._replace(link="tcp")])
        for row, figures in rows.items()
        if row.link == "unixsock" and row._replace(link="tcp") in rows
    ]
    if not pairs:
        return
    print("unixsock / tcp, same run:")
    print("sonar      topology  transport   robots  p50_ratio  p99_ratio")
    for row, (p50, p99), (tcp_p50, tcp_p99) in pairs:
        print(
            f"{row.sonar:9s}  {row.topology:8s}  {row.transport:10s}  {row.robots:6d}  "
            f"{p50 / tcp_p50:9.3f}  {p99 / tcp_p99:9.3f}"
        )


if __name__ == "__main__":
    main()
