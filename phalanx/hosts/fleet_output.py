"""What `phalanx launch` and `phalanx status` show: the fleet's status table and its output.

One `Row` per robot (its host, process state, restarts, behaviour state, leader,
publication rate, last error) and one for the world (its progress in ticks); shown as
plain lines (`PlainOutput`), a live rich table (`LiveOutput`, `render_table`) or JSON
(`status_document`).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from phalanx.core.config import Scenario
from phalanx.core.lifecycle import Closing
from phalanx.hosts.deployment import LoadedDeployment
from phalanx.hosts.fleet_client import FleetWatch
from phalanx.hosts.protocol import ChildStatus, HostStatus, LogLine


@dataclass(frozen=True)
class Row:
    """One line of the status table."""

    name: str
    host: str
    process: str
    restarts: int
    state: str
    leader: str
    rate_hz: float | None
    last_error: str
    dropped: int | None = None  # payloads the process dropped (malformed, ring, refused)
    relinks: int | None = None  # times the process re-opened its Zenoh session (deaf)


class Output(Protocol):
    """Where a launcher shows what happens (a live table, or plain lines)."""

    def event(self, text: str) -> None:
        """Something worth a line of its own."""

    def log(self, line: LogLine) -> None:
        """A child's output line."""

    def update(self, rows: list[Row]) -> None:
        """The fleet now."""


def fleet_rows(
    loaded: LoadedDeployment,
    statuses: dict[str, HostStatus | None],
    watch: FleetWatch,
    *,
    world: dict[str, Any] | None = None,
    total_ticks: int | None = None,
    processes: dict[str, dict[str, Any]] | None = None,
) -> list[Row]:
    """The status table: one row per robot, and the world (`tick k/total_ticks`), with
    what each process dropped (`processes`: their own status replies).
    """
    now = time.monotonic()
    processes = processes or {}
    if world is not None:
        processes = {"world": world, **processes}
    present = watch.present()
    rows = []
    for placement in loaded.spec.robots:
        child = _child(statuses, placement.host, placement.id)
        state = watch.state(placement.id)
        rows.append(
            Row(
                name=placement.id,
                host=placement.host,
                process=_process(child, placement.host in present),
                restarts=child.restarts if child else 0,
                state=state.fsm_state if state else "-",
                leader=(state.leader_id or "-") if state else "-",
                rate_hz=watch.rate_hz(placement.id, now),
                last_error=child.last_error if child else "",
                dropped=_counter(processes.get(placement.id), "dropped"),
                relinks=_counter(processes.get(placement.id), "relinks"),
            )
        )
    if loaded.spec.world is not None:
        host = loaded.spec.world.host
        child = _child(statuses, host, "world")
        process = _process(child, host in present)
        error = child.last_error if child else ""
        progress = _world_state(world, total_ticks or scenario_ticks(loaded.scenario))
        dropped, relinks = (_counter(processes.get("world"), c) for c in ("dropped", "relinks"))
        rows.append(Row("world", host, process, 0, progress, "-", None, error, dropped, relinks))
    return rows


def _counter(status: dict[str, Any] | None, name: str) -> int | None:
    value = status.get(name) if status else None
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def scenario_ticks(scenario: Scenario) -> int:
    """The control steps of a whole run of `scenario`."""
    return round(scenario.duration_s * scenario.control_rate_hz)


def _world_state(world: dict[str, Any] | None, total_ticks: int) -> str:
    if not world or "tick" not in world:
        return "-"
    return f"tick {world['tick']}/{total_ticks}"


def _child(statuses: dict[str, HostStatus | None], host: str, name: str) -> ChildStatus | None:
    status = statuses.get(host)
    if status is None:
        return None
    return next((c for c in status.children if c.name == name), None)


def _process(child: ChildStatus | None, host_present: bool) -> str:
    if not host_present:
        return "host lost"
    return child.state if child is not None else "-"


def rows_as_json(rows: list[Row]) -> list[dict[str, Any]]:
    """The table as plain data."""
    return [row.__dict__ for row in rows]


class PlainOutput:
    """Lines: events, log lines, every change of a row, the world's progress now and then."""

    def __init__(
        self, write: Callable[[str], None], *, logs: bool = True, progress_s: float = 10.0
    ) -> None:
        self.write = write
        self.logs = logs
        self.progress_s = progress_s
        self._last: dict[str, tuple[str, str, str]] = {}
        self._progress_at = time.monotonic()

    def event(self, text: str) -> None:
        """Print an event."""
        self.write(f"{_clock()} {text}")

    def log(self, line: LogLine) -> None:
        """Print a child's line, prefixed with host/child."""
        if self.logs:
            self.write(f"{_clock()} [{line.host}/{line.child}] {line.line}")

    def update(self, rows: list[Row]) -> None:
        """Print the rows that changed."""
        now = time.monotonic()
        for row in rows:
            ticking = row.name == "world" and row.state.startswith("tick ")
            key = (row.process, "tick" if ticking else row.state, row.leader)
            if ticking and now - self._progress_at > self.progress_s:
                self._progress_at = now
                self.write(f"{_clock()} world on {row.host}: {row.state}")
            if self._last.get(row.name) != key:
                self._last[row.name] = key
                leader = f" (leader {row.leader})" if row.leader != "-" else ""
                self.write(
                    f"{_clock()} {row.name} on {row.host}: {row.process}, {row.state}{leader}"
                )


def _clock() -> str:
    return time.strftime("%H:%M:%S")


def render_table(rows: list[Row], *, title: str) -> Any:
    """A rich Table of the rows."""
    from rich.table import Table

    table = Table(title=title, expand=False)
    columns = ("robot", "host", "process", "restarts", "state", "leader", "rate", "dropped",
               "relinks", "last error")  # fmt: skip
    for column in columns:
        table.add_column(column, no_wrap=column != "last error", overflow="fold")
    for row in rows:
        rate = f"{row.rate_hz:.1f} Hz" if row.rate_hz is not None else "-"
        table.add_row(
            row.name,
            row.host,
            _styled(row.process),
            str(row.restarts),
            row.state,
            row.leader,
            rate,
            "-" if row.dropped is None else str(row.dropped),
            "-" if row.relinks is None else str(row.relinks),
            row.last_error[-80:],
        )
    return table


def _styled(process: str) -> str:
    colour = {"running": "green", "failed": "red", "host lost": "red", "backoff": "yellow"}
    return f"[{colour[process]}]{process}[/]" if process in colour else process


class LiveOutput(Closing):
    """A live rich table; events and log lines scroll above it. Context manager."""

    def __init__(self, title: str, *, logs: bool = True) -> None:
        from rich.console import Console
        from rich.live import Live

        self.title = title
        self.logs = logs
        self.console = Console()
        self.live = Live(render_table([], title=title), console=self.console, refresh_per_second=4)
        self.live.start()

    def event(self, text: str) -> None:
        """Print an event above the table."""
        self.console.print(f"{_clock()} {text}", markup=False, highlight=False)

    def log(self, line: LogLine) -> None:
        """Print a child's line above the table."""
        if self.logs:
            style = {"error": "red", "warning": "yellow"}.get(line.level)
            self.console.print(
                f"[{line.host}/{line.child}] {line.line}",
                style=style,
                markup=False,
                highlight=False,
            )

    def update(self, rows: list[Row]) -> None:
        """Redraw the table."""
        self.live.update(render_table(rows, title=self.title))

    def close(self) -> None:
        """Stop redrawing; safe twice."""
        self.live.stop()


def status_document(
    statuses: dict[str, HostStatus | None], rows: list[Row], skews: dict[str, float]
) -> str:
    """`phalanx status --json`: hosts (None if absent), robots, clock skews."""
    hosts = {h: (s.model_dump() if s is not None else None) for h, s in statuses.items()}
    return json.dumps(
        {"hosts": hosts, "robots": rows_as_json(rows), "clock_skew_s": skews}, indent=2
    )
