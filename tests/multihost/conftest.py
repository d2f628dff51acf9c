"""Fixtures for fleets across hosts: deployment files, host daemons, network namespaces."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import netlab
import pytest
from netlab import NetLab, unavailable

from phalanx.core.config_files import CONFIG_ROOT

WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
PYTHON = sys.executable
CLI = [PYTHON, "-m", "phalanx"]
NETLAB = netlab.__file__  # run as a script: `python netlab.py observe ...`
LAB_HOSTS = ("world", "robot-a", "robot-b")
PLACEMENT = {"r1": "robot-a", "r2": "robot-b", "r3": "robot-b"}


def deployment_text(
    *,
    name: str,
    hosts: Sequence[tuple[str, str, int]],
    out_dir: Path,
    clock: str = "lockstep",
    lease_ms: int = 500,
    placement: dict[str, str] | None = None,
    world_host: str = "world",
    extra: str = "",
    zenoh_extra: str = "",
    security: str = 'mode = "open"',
) -> str:
    """A deployment file for the paper wedge: hosts as (name, address, port). Open links
    unless `security` says otherwise (test_security.py secures them)."""
    lines = [
        f'name = "{name}"',
        f'fleet = "{name}"',
        f'scenario = "{WEDGE}"',
        f'clock = "{clock}"',
        extra,
        "[security]",
        security,
        "[zenoh]",
        f"lease_ms = {lease_ms}",
        "retry_max_ms = 500",
        zenoh_extra,
        "[world]",
        f'host = "{world_host}"',
        f'out_dir = "{out_dir}"',
        "recording = false",
    ]
    for host, address, port in hosts:
        lines += ["[[hosts]]", f'name = "{host}"', f'address = "{address}"', f"port = {port}"]
    for rid, host in (placement or PLACEMENT).items():
        lines += ["[[robots]]", f'id = "{rid}"', f'host = "{host}"']
    return "\n".join(lines) + "\n"


@dataclass
class Daemons:
    """Host daemons started by a test; stopped (SIGTERM, then SIGKILL) at its end."""

    logs: Path
    procs: dict[str, subprocess.Popen[bytes]] = field(default_factory=dict)

    def log_tail(self, chars: int = 3000) -> str:
        """The end of every daemon's log, for assertion messages."""
        parts = []
        for name in self.procs:
            text = (self.logs / f"host-{name}.log").read_text(errors="replace")
            parts.append(f"--- host {name} ---\n{text[-chars:]}")
        return "\n".join(parts)

    def stop(self, timeout_s: float = 20.0) -> dict[str, int]:
        """SIGTERM every daemon; their exit codes (SIGKILL after `timeout_s`)."""
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        codes = {}
        for name, proc in self.procs.items():
            try:
                codes[name] = proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                codes[name] = proc.wait(5)
        return codes


def start_daemons(
    deployment: Path,
    names: Sequence[str],
    logs: Path,
    *,
    wrap: Callable[[str, list[str]], list[str]] = lambda _h, argv: argv,
) -> Daemons:
    """`phalanx host DEPLOYMENT --name NAME` for each name (`wrap`: e.g. into a namespace)."""
    logs.mkdir(parents=True, exist_ok=True)
    daemons = Daemons(logs)
    for name in names:
        argv = wrap(name, [*CLI, "host", str(deployment), "--name", name])
        with (logs / f"host-{name}.log").open("wb") as sink:
            daemons.procs[name] = subprocess.Popen(argv, stdout=sink, stderr=subprocess.STDOUT)
    return daemons


@pytest.fixture(scope="module")
def lab() -> Iterator[NetLab]:
    """Three hosts in network namespaces on one bridge (skipped where not allowed)."""
    reason = unavailable()
    if reason is not None:
        pytest.skip(f"no network namespaces on this machine: {reason}")
    with NetLab(LAB_HOSTS) as made:
        yield made


class Observer:
    """`python netlab.py observe` in a namespace; its JSON lines, as they come."""

    def __init__(self, argv: list[str]) -> None:
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        self.records: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            with self._lock:
                self.records.append(json.loads(raw))

    def wait_for(
        self, predicate: Callable[[list[dict[str, Any]]], bool], timeout_s: float
    ) -> float | None:
        """CLOCK_MONOTONIC when `predicate(records)` first held, or None on timeout."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                records = list(self.records)
            if predicate(records):
                return time.monotonic()
            time.sleep(0.02)
        return None

    def snapshot(self) -> list[dict[str, Any]]:
        """Every record so far."""
        with self._lock:
            return list(self.records)

    def close(self) -> None:
        """Stop the observer; safe twice."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._reader.join(2)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


class Kit:
    """The helpers above, for test modules (which cannot import a conftest)."""

    CLI = CLI
    PYTHON = PYTHON
    NETLAB = NETLAB
    WEDGE = WEDGE
    LAB_HOSTS = LAB_HOSTS
    deployment_text = staticmethod(deployment_text)
    start_daemons = staticmethod(start_daemons)
    Observer = Observer


@pytest.fixture
def kit() -> Kit:
    """Deployment files, daemons and observers for multi-host tests."""
    return Kit()


@pytest.fixture(scope="module")
def module_kit() -> Kit:
    """The same, for module-scoped fixtures (daemons shared by a module's tests)."""
    return Kit()
