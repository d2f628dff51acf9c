"""`phalanx launch`: a deployed fleet run to its end through its hosts' daemons.

The launcher waits (bounded) for every host of the deployment to be present and to hold
the same deployment and scenario files, asks each host to spawn its part of the run,
then follows the run: the hosts' status queryables (process states, restarts, last
errors), the robots' own state messages (behaviour state, leader, publication rate) and
the children's output (log lines the daemons publish). It ends when every process has
ended, on its timeout, or on Ctrl-C, and then asks every host to stop what is left.

Its exit code is `phalanx.runtime.exits`': 0 only when the world's results say the run
is complete (the world exits 5 when they do not, 6 when it could not write them), 1
when a process died or a host was lost, or on a timeout or Ctrl-C. Each is named.
"""

from __future__ import annotations

import queue
import time
from dataclasses import dataclass, field

from phalanx.core.config_files import apply_overrides
from phalanx.hosts.deployment import LoadedDeployment, needs_epoch
from phalanx.hosts.fleet_client import FleetClient, FleetWatch
from phalanx.hosts.fleet_output import Output, fleet_rows, scenario_ticks
from phalanx.hosts.protocol import ACTIVE_STATES, ChildStatus, HostStatus
from phalanx.runtime.exits import EXIT_FAILED, EXIT_FINISHED, EXIT_INCOMPLETE, EXIT_RESULTS_LOST
from phalanx.runtime.signals import Stoppable
from phalanx.wire.transport import TransportConfig

POLL_S = 0.5


@dataclass
class LaunchOptions:
    """What `phalanx launch` does beyond the deployment file."""

    run_id: str
    overrides: tuple[str, ...] = ()
    host_wait_s: float = 30.0
    timeout_s: float | None = None  # default: the scenario's duration plus a margin
    detach: bool = False  # return once the fleet is up; `phalanx stop` ends it
    finish_grace_s: float = 15.0  # agents still running this long after the world ended


@dataclass
class _Run:
    started: float
    spawned: float = 0.0
    up_at: float | None = None
    world_done_at: float | None = None
    statuses: dict[str, HostStatus | None] = field(default_factory=dict)
    results: list[str] = field(default_factory=list)
    incomplete: str | None = None  # why the world's results say the run is incomplete
    hosts_lost: set[str] = field(default_factory=set)  # hosts whose daemon is out of sight


def launch(
    loaded: LoadedDeployment,
    options: LaunchOptions,
    *,
    transport: TransportConfig,
    output: Output,
    stop: Stoppable,
) -> int:
    """Run a deployment to its end (or Ctrl-C, or the timeout); the exit code."""
    run = _Run(started=time.monotonic())
    with FleetClient(loaded, transport) as client:
        client.wait_for_hosts(options.host_wait_s, output.event, stop)
        if stop.is_set():
            output.event("interrupted while waiting for the hosts")
            return 1
        output.event(
            f"hosts present: {', '.join(client.host_names)} "
            f"({time.monotonic() - run.started:.2f} s)"
        )
        epoch = time.time() + loaded.spec.startup_s if needs_epoch(loaded) else None
        try:
            run.statuses = dict(
                client.spawn(options.run_id, overrides=options.overrides, epoch_unix=epoch)
            )
            run.spawned = time.monotonic()
            output.event(f"run {options.run_id} started ({run.spawned - run.started:.2f} s)")
            code = _follow(client, loaded, options, run, output, stop)
        except BaseException:  # whatever started must not outlive a failed launch
            _stop_everything(client, options, output)
            raise
        if not options.detach or code != 0:
            _stop_everything(client, options, output)
            _drain_logs(client.watch, output, run)
        for line in run.results:
            output.event(line)
        problems = [f"host {h}: its daemon went away" for h in sorted(run.hosts_lost)]
        problems += deaths(run.statuses)
        for problem in problems:
            output.event(f"ended unexpectedly: {problem}")
        if code == EXIT_INCOMPLETE:
            why = run.incomplete or "see incomplete_reason in metrics.json on the world's host"
            output.event(f"the run is incomplete: {why}")
    return EXIT_FAILED if problems and code in (EXIT_FINISHED, EXIT_INCOMPLETE) else code


def deaths(statuses: dict[str, HostStatus | None]) -> list[str]:
    """Every process of the run that died on its own (crashed, restarted or failed), with
    why: a run with any is not a clean finish, whatever the world says.
    """
    out = []
    for host, status in statuses.items():
        for child in status.children if status is not None else ():
            if child.crashes or child.state == "failed":
                restarted = f", restarted {child.restarts}x" if child.restarts else ""
                out.append(f"{child.name} on {host}: {child.last_error or child.state}{restarted}")
    return out


def _follow(
    client: FleetClient,
    loaded: LoadedDeployment,
    options: LaunchOptions,
    run: _Run,
    output: Output,
    stop: Stoppable,
) -> int:
    timeout_s = options.timeout_s or _default_timeout_s(loaded)
    deadline = run.started + timeout_s
    robots = [r.id for r in loaded.spec.robots]
    overrides = list(options.overrides)
    ticks = scenario_ticks(
        apply_overrides(loaded.scenario, overrides, source=str(loaded.scenario_path))
    )
    while not stop.wait(POLL_S):
        _drain_logs(client.watch, output, run)
        _watch_hosts(client, run, output)
        run.statuses.update(client.statuses())
        processes = client.process_statuses(0.3)
        rows = fleet_rows(
            loaded, run.statuses, client.watch, world=processes.get("world"),
            total_ticks=ticks, processes=processes,
        )  # fmt: skip
        output.update(rows)
        if run.up_at is None and client.watch.seen_since(robots, run.spawned):
            run.up_at = time.monotonic()
            output.event(f"fleet up in {run.up_at - run.started:.2f} s (every robot publishing)")
            if options.detach:
                return 0
        code = _finished(run, loaded, options)
        if code is not None:
            return code
        if time.monotonic() > deadline:
            output.event(f"timed out after {timeout_s:.0f} s")
            return 1
    output.event("interrupted")
    return 1


def _watch_hosts(client: FleetClient, run: _Run, output: Output) -> None:
    """Say when a host's daemon goes out of sight, and when it is back (a host still out
    of sight at the end is an ending that was not asked for).
    """
    present = client.watch.present()
    for host in sorted(set(client.host_names) - present - run.hosts_lost):
        output.event(f"host {host} lost (its daemon's liveliness token is gone)")
        run.hosts_lost.add(host)
    for host in sorted(run.hosts_lost & present):
        output.event(f"host {host} is back")
        run.hosts_lost.discard(host)


def _default_timeout_s(loaded: LoadedDeployment) -> float:
    speed = loaded.spec.world.speed if loaded.spec.world else 1.0
    return loaded.scenario.duration_s / speed + loaded.spec.startup_s + 120.0


def _finished(run: _Run, loaded: LoadedDeployment, options: LaunchOptions) -> int | None:
    children = [c for s in run.statuses.values() if s is not None for c in s.children]
    world = [c for c in children if c.kind == "world"]
    if world and world[0].state == "failed":
        return world_code(world[0])
    if world and world[0].state in ("finished", "stopped"):
        run.world_done_at = run.world_done_at or time.monotonic()
        late = time.monotonic() - run.world_done_at > options.finish_grace_s
        if late or not any(c.state in ACTIVE_STATES for c in children):
            return world_code(world[0])
        return None
    if loaded.spec.world is not None or not children:
        return None
    if any(c.state in ACTIVE_STATES for c in children):
        return None
    return 1 if any(c.state == "failed" for c in children) else 0


def world_code(world: ChildStatus) -> int:
    """The launch's exit code from its ended world: finished with a complete run (0) or
    an incomplete one (5); its results not written (6); anything else (1).
    """
    if world.state == "finished":
        return EXIT_INCOMPLETE if world.exit_code == EXIT_INCOMPLETE else EXIT_FINISHED
    return EXIT_RESULTS_LOST if world.exit_code == EXIT_RESULTS_LOST else EXIT_FAILED


def _stop_everything(client: FleetClient, options: LaunchOptions, output: Output) -> None:
    replies = client.stop(options.run_id)
    for host, reply in replies.items():
        if reply is None:
            output.event(f"host {host} did not answer the stop request")
    left = client.wait_stopped(timeout_s=15.0)
    if left:
        output.event(f"still running after the stop request: {', '.join(left)}")


def _drain_logs(watch: FleetWatch, output: Output, run: _Run) -> None:
    while True:
        try:
            line = watch.logs.get_nowait()
        except queue.Empty:
            return
        if line.child == "world" and line.line.startswith("results: "):
            folder = line.line.removeprefix("results: ")
            run.results.append(f"results on host {line.host}: {folder}")
        if line.child == "world" and line.line.startswith("incomplete run: "):
            run.incomplete = line.line.removeprefix("incomplete run: ")
        output.log(line)
