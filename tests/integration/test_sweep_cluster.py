"""`phalanx sweep --address` on a Dask cluster of separate processes: a scheduler and two
workers started with Dask's own `dask scheduler` and `dask worker` on loopback, as they
would be on other hosts. One worker is killed with SIGKILL while the sweep runs (a host
lost): the scheduler gives its runs to the other, the sweep finishes, every run finished
before the kill is in the results file exactly once, and a sweep started again runs
nothing.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.timeout(420)]

BIN = Path(sys.executable).parent
SEEDS = 10  # x the three formations: 30 runs
RUN_S = 30.0  # each run's simulated time: about a second of work on one core
KILL_AFTER_ROWS = 5  # the first worker dies once this many runs are in the file
START_TIMEOUT_S = 60.0  # a scheduler or a worker up and registered
SWEEP_TIMEOUT_S = 300.0
STOP_TIMEOUT_S = 10.0


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

    def _start(self, name: str, args: list[str]) -> Daemon:
        log = self.folder / f"{name}.log"
        with log.open("wb") as sink:
            process = subprocess.Popen(
                [str(BIN / "dask"), *args], stdout=sink, stderr=subprocess.STDOUT,
                cwd=self.folder, start_new_session=True,
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

    def worker(self, name: str) -> Daemon:
        """Start a worker of one process and one thread, registered with the scheduler."""
        daemon = self._start(
            name,
            [
                "worker", self.address, "--name", name, "--host", "127.0.0.1",
                "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
                "--local-directory", str(self.folder / name),
            ],
        )  # fmt: skip
        _wait(lambda: "Registered to" in daemon.text(), daemon)
        return daemon

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
            pytest.fail(f"{daemon.name} exited: {daemon.text()[-2000:]}")
        if time.monotonic() > deadline:
            pytest.fail(f"{daemon.name} not ready in {START_TIMEOUT_S} s: {daemon.text()[-2000:]}")
        time.sleep(0.1)


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    """A cluster stopped at the end; the test fails if any of its processes outlives it."""
    made = Cluster(tmp_path)
    try:
        yield made
    finally:
        made.close()
    leaked = made.leftovers()
    if leaked:
        for pid in leaked:
            os.kill(pid, signal.SIGKILL)
        pytest.fail(f"the cluster left processes running: {leaked}")


def _sweep_command(address: str, out: Path) -> list[str]:
    return [
        str(BIN / "phalanx"), "sweep", "--seeds", str(SEEDS), "--address", address,
        "--out", str(out), "--set", f"duration_s={RUN_S}",
    ]  # fmt: skip


def _keys(out: Path) -> list[str]:
    """The job key of every line of a results file, in order (repeats kept)."""
    if not out.exists():
        return []
    return [json.loads(line)["key"] for line in out.read_text(encoding="utf-8").splitlines()]


def _wait_for_rows(out: Path, rows: int, sweep: subprocess.Popen[bytes]) -> list[str]:
    """The keys in `out` once it holds `rows` finished runs (the sweep still going)."""
    deadline = time.monotonic() + SWEEP_TIMEOUT_S
    while len(keys := _keys(out)) < rows:
        assert sweep.poll() is None, "the sweep ended before any worker was killed"
        assert time.monotonic() < deadline, f"{len(keys)} runs in {SWEEP_TIMEOUT_S} s"
        time.sleep(0.05)
    return keys


def test_a_sweep_outlives_a_killed_worker_loses_no_run_and_resumes(
    cluster: Cluster, tmp_path: Path
) -> None:
    address = cluster.scheduler()
    doomed = cluster.worker("w1")
    cluster.worker("w2")
    out, said = tmp_path / "runs.jsonl", tmp_path / "sweep.err"
    with said.open("wb") as err:
        sweep = subprocess.Popen(
            _sweep_command(address, out), stdout=subprocess.DEVNULL, stderr=err
        )
    try:
        before_kill = _wait_for_rows(out, KILL_AFTER_ROWS, sweep)
        cluster.kill(doomed)
        assert sweep.wait(SWEEP_TIMEOUT_S) == 0, said.read_text(encoding="utf-8")
    finally:
        if sweep.poll() is None:
            sweep.kill()
            sweep.wait(STOP_TIMEOUT_S)
    keys = _keys(out)
    assert len(keys) == len(set(keys)) == 3 * SEEDS, keys
    assert len(before_kill) < 3 * SEEDS  # (killed mid-way)
    assert set(before_kill) <= set(keys)
    scheduler = cluster.daemons[0].text()
    assert "Remove worker addr" in scheduler, scheduler[-2000:]
    assert "name: w1" in scheduler
    progress = said.read_text(encoding="utf-8")
    assert f"(the cluster at {address} may have more)" in progress
    assert "left" in progress  # (the estimate of the time left, while it runs)
    assert f"{3 * SEEDS} of {3 * SEEDS} runs (100 %)" in progress

    text = out.read_text(encoding="utf-8")
    again = subprocess.run(
        _sweep_command(address, out), capture_output=True, text=True,
        timeout=SWEEP_TIMEOUT_S, check=True,
    )  # fmt: skip
    assert again.stderr.startswith("0 runs to do"), again.stderr
    assert out.read_text(encoding="utf-8") == text
