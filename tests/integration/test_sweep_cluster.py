"""`phalanx sweep --address` on a Dask cluster of separate processes: a scheduler and two
workers started with Dask's own `dask scheduler` and `dask worker` on loopback, as they
would be on other hosts. One worker is killed with SIGKILL while the sweep runs (a host
lost): the scheduler gives its runs to the other, the sweep finishes, every run finished
before the kill is in the results file exactly once, and a sweep started again runs
nothing. A worker started with docs/SWEEPS.md's configuration file runs with the settings
`phalanx sweep` gives its own local workers.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from dask_cluster import BIN, STOP_TIMEOUT_S, Cluster, result_keys, worker_config_file

from phalanx.analysis.sweep import QUIET_DASK

pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.timeout(420)]

SEEDS = 10  # x the three formations: 30 runs
RUN_S = 30.0  # each run's simulated time: about a second of work on one core
KILL_AFTER_ROWS = 15  # the first worker dies once this many runs are in the file
# Runs the dead worker had finished and not handed over yet (done again elsewhere): the
# one or two it may have just finished while the sweep, on a loaded machine, had not
# fetched them; a sweep that kept every result on its worker loses the half of the 15
# it did.
LOST_AT_MOST = 3
SWEEP_TIMEOUT_S = 300.0


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


def _wait_for_rows(out: Path, rows: int, sweep: subprocess.Popen[bytes]) -> list[str]:
    """The keys in `out` once it holds `rows` finished runs (the sweep still going)."""
    deadline = time.monotonic() + SWEEP_TIMEOUT_S
    while len(keys := result_keys(out)) < rows:
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
    keys = result_keys(out)
    assert len(keys) == len(set(keys)) == 3 * SEEDS, keys
    assert len(before_kill) < 3 * SEEDS  # (killed mid-way)
    assert set(before_kill) <= set(keys)
    scheduler = cluster.daemons[0].text()
    assert "Remove worker addr" in scheduler, scheduler[-2000:]
    assert "name: w1" in scheduler
    assert len(cluster.lost_results()) <= LOST_AT_MOST, scheduler[-3000:]
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


def test_a_worker_started_with_the_docs_configuration_file_runs_as_the_sweeps_own(
    cluster: Cluster, tmp_path: Path
) -> None:
    """docs/SWEEPS.md's configuration file, read by `dask worker` through DASK_CONFIG,
    gives the worker process what `phalanx sweep` gives its own: glibc's threshold for
    handing memory back above the nanny's 65536, and Dask's housekeeping as QUIET_DASK has
    it.
    """
    folder = tmp_path / "worker-config"
    folder.mkdir()
    (folder / "phalanx.yaml").write_text(worker_config_file(), encoding="utf-8")
    address = cluster.scheduler()
    cluster.worker("w1", config=folder)
    probe = (
        "import json, os, sys, dask\n"
        "from dask.distributed import Client\n"
        "from phalanx.analysis.sweep import QUIET_DASK\n"
        "with Client(sys.argv[1], timeout=30) as client:\n"
        "    seen = client.run(lambda: (os.environ.get('MALLOC_TRIM_THRESHOLD_'), "
        "{k: dask.config.get(k) for k in QUIET_DASK}))\n"
        "print(json.dumps(list(seen.values())))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe, address], capture_output=True, text=True, timeout=120,
        check=True, env={k: v for k, v in os.environ.items() if k != "DASK_CONFIG"},
    )  # fmt: skip
    ((threshold, housekeeping),) = json.loads(done.stdout.strip().splitlines()[-1])
    assert int(threshold) > 65536
    assert housekeeping == QUIET_DASK
