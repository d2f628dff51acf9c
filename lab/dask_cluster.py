"""A Dask cluster of separate processes on loopback, as it would be on other hosts: a
`dask scheduler` and `dask worker`s started with Dask's own commands, each in a session
of its own, killed as a lost host is (SIGKILL to a worker and its nanny at once), and
stopped with nothing left running. Used by the sweep's cluster test and its benchmark.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

BIN = Path(sys.executable).parent
SWEEPS_DOC = Path(__file__).resolve().parents[1] / "docs" / "SWEEPS.md"
START_TIMEOUT_S = 60.0  # a scheduler or a worker up and registered
STOP_TIMEOUT_S = 10.0


def result_keys(results: Path) -> list[str]:
    """The job key of every line of a sweep's results file, in order, repeats kept (a
    line the sweep is still writing is left out).
    """
    if not results.exists():
        return []
    keys = []
    for line in results.read_text(encoding="utf-8").splitlines():
        try:
            keys.append(json.loads(line)["key"])
        except json.JSONDecodeError:
            continue
    return keys


def worker_config_file() -> str:
    """The Dask configuration file docs/SWEEPS.md gives workers started by hand (its
    one YAML block, as a file holds it).
    """
    (block,) = re.findall(r"```yaml\n(.*?)```", SWEEPS_DOC.read_text(encoding="utf-8"), re.S)
    return re.sub(r"(?m)^ {2}", "", block)  # (the block is indented under its bullet)


class ClusterError(RuntimeError):
    """A scheduler or worker that exited or did not come up in time."""


@dataclass
class Daemon:
    """One `dask` process in a session of its own (its group id is its pid), with its log."""

    name: str
    process: subprocess.Popen[bytes]
    log: Path

    def text(self) -> str:
        """What it has logged so far."""
        return self.log.read_text(encoding="utf-8", errors="replace")


class Cluster:
    """A scheduler and its workers as separate processes; `close` stops every one."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.daemons: list[Daemon] = []
        self.address = ""

    def _start(self, name: str, args: list[str], env: dict[str, str] | None = None) -> Daemon:
        log = self.folder / f"{name}.log"
        with log.open("wb") as sink:
            process = subprocess.Popen(
                [str(BIN / "dask"), *args], stdout=sink, stderr=subprocess.STDOUT,
                cwd=self.folder, start_new_session=True, env=env,
            )  # fmt: skip
        daemon = Daemon(name, process, log)
        self.daemons.append(daemon)
        return daemon

    def scheduler(self) -> str:
        """Start the scheduler on a free loopback port; its address (tcp://127.0.0.1:N)."""
        info = self.folder / "scheduler.json"
        daemon = self._start(
            "scheduler",
            ["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
             "--scheduler-file", str(info)],
        )  # fmt: skip
        _wait(lambda: info.exists() and "address" in info.read_text(encoding="utf-8"), daemon)
        self.address = json.loads(info.read_text(encoding="utf-8"))["address"]
        return self.address

    def worker(self, name: str, config: Path | None = None) -> Daemon:
        """Start a worker of one process and one thread, registered with the scheduler;
        `config`: a folder of Dask configuration files it reads (`DASK_CONFIG`).
        """
        env = None if config is None else {**os.environ, "DASK_CONFIG": str(config)}
        daemon = self._start(
            name,
            [
                "worker", self.address, "--name", name, "--host", "127.0.0.1",
                "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
                "--local-directory", str(self.folder / name),
            ],
            env,
        )  # fmt: skip
        _wait(lambda: "Registered to" in daemon.text(), daemon)
        return daemon

    def lost_results(self) -> set[str]:
        """The finished tasks the scheduler says removed workers took with it (to be done
        again elsewhere): the keys in its "lose already computed task(s)" warnings.
        """
        lost: set[str] = set()
        scheduler = next(d for d in self.daemons if d.name == "scheduler")
        for line in scheduler.text().splitlines():
            if "lose already computed task(s)" in line:
                lost.update(re.findall(r"'([^']+)'", line.split("elsewhere:", 1)[-1]))
        return lost

    def kill(self, daemon: Daemon) -> None:
        """SIGKILL to the worker and its nanny at once: a host lost, not a shutdown."""
        os.killpg(daemon.process.pid, signal.SIGKILL)
        daemon.process.wait(STOP_TIMEOUT_S)

    def close(self) -> None:
        """SIGTERM to every group, SIGKILL to what is left after STOP_TIMEOUT_S."""
        for daemon in self.daemons:
            _signal_group(daemon.process.pid, signal.SIGTERM)
        deadline = time.monotonic() + STOP_TIMEOUT_S
        while self.leftovers() and time.monotonic() < deadline:
            time.sleep(0.1)
        for daemon in self.daemons:
            _signal_group(daemon.process.pid, signal.SIGKILL)
            daemon.process.wait(STOP_TIMEOUT_S)

    def leftovers(self) -> list[int]:
        """The processes still alive in the groups this cluster started."""
        groups = {daemon.process.pid for daemon in self.daemons}
        return [pid for pid, group in _process_groups() if group in groups]


def _signal_group(group: int, sig: signal.Signals) -> None:
    with contextlib.suppress(ProcessLookupError):  # (the whole group is gone already)
        os.killpg(group, sig)


def _process_groups() -> list[tuple[int, int]]:
    """(pid, process group) of every live process on this machine."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except (FileNotFoundError, ProcessLookupError):
            continue  # (it ended while we looked)
        if fields[0] != "Z":
            out.append((int(entry.name), int(fields[2])))
    return out


def _wait(ready: Callable[[], bool], daemon: Daemon) -> None:
    """Until `ready()` holds; fail if `daemon` dies or START_TIMEOUT_S passes."""
    deadline = time.monotonic() + START_TIMEOUT_S
    while not ready():
        if daemon.process.poll() is not None:
            raise ClusterError(f"{daemon.name} exited: {daemon.text()[-2000:]}")
        if time.monotonic() > deadline:
            raise ClusterError(
                f"{daemon.name} not ready in {START_TIMEOUT_S} s: {daemon.text()[-2000:]}"
            )
        time.sleep(0.1)
