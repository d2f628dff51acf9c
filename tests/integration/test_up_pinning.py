"""`phalanx up` pins its processes to CPUs in lockstep: the plan gives each one CPU
(the world first, the robots sharing its CPU last), and a started process runs there
with every thread it makes later; a CPU the system refuses leaves it running unpinned."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.runtime.local_fleet import (
    Child,
    UpOptions,
    assign_cpus,
    pin_process,
    plan,
    usable_cpus,
)

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(
        not hasattr(os, "sched_setaffinity"), reason="this platform cannot pin a process"
    ),
]
WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
CPUS = usable_cpus()
two_cpus = pytest.mark.skipif(len(CPUS) < 2, reason="pinning needs two usable CPUs")

# Starts a thread a moment after it starts (after `pin_process` has run), then waits.
LATE_THREAD = """
import threading, time
time.sleep(0.3)
threading.Thread(target=time.sleep, args=(30,), daemon=True).start()
time.sleep(30)
"""


@two_cpus
def test_lockstep_pins_every_process_the_world_first() -> None:
    children = plan(WEDGE, load_scenario(WEDGE), UpOptions(fleet="pin"))
    assert [c.name for c in children] == ["world", "r1", "r2", "r3"]
    reference = [Child(c.name, []) for c in children]
    assign_cpus(reference, CPUS)
    assert [c.cpu for c in children] == [c.cpu for c in reference]


@pytest.mark.parametrize(("robots", "cpus"), [(3, 2), (5, 2), (3, 4), (7, 3), (1, 2), (2, 8)])
def test_cpus_are_shared_evenly_and_the_worlds_by_the_last_robots(robots: int, cpus: int) -> None:
    children = [Child("world", []), *(Child(f"r{i}", []) for i in range(1, robots + 1))]
    given = [10 + 2 * c for c in range(cpus)]  # (any CPU numbers, in order)
    assign_cpus(children, given)
    on = [c.cpu for c in children]
    assert on[0] == given[0]
    counts = sorted((on.count(c) for c in given), reverse=True)
    assert counts[0] - counts[-1] <= 1  # as even as round robin
    assert sum(counts) == robots + 1
    mates = [i for i, c in enumerate(on[1:]) if c == given[0]]
    assert mates == list(range(robots - len(mates), robots))  # the world's CPU: the last
    if (robots, cpus) == (3, 2):
        assert on == [10, 12, 12, 10]


def test_one_cpu_pins_nothing() -> None:
    children = [Child("world", []), Child("r1", [])]
    assign_cpus(children, [0])
    assert [c.cpu for c in children] == [None, None]


@two_cpus
def test_realtime_runs_unpinned_unless_asked_and_no_pin_is_heard() -> None:
    scenario = load_scenario(WEDGE)
    realtime = plan(WEDGE, scenario, UpOptions(fleet="pin", clock="realtime"))
    assert all(c.cpu is None for c in realtime)
    asked = plan(WEDGE, scenario, UpOptions(fleet="pin", clock="realtime", pin=True))
    assert [c.cpu for c in asked] == [c.cpu for c in plan(WEDGE, scenario, UpOptions(fleet="p"))]
    assert all(c.cpu is not None for c in asked)
    refused = plan(WEDGE, scenario, UpOptions(fleet="pin", pin=False))
    assert all(c.cpu is None for c in refused)


def _threads(pid: int) -> list[int]:
    return [int(t) for t in os.listdir(f"/proc/{pid}/task")]


@two_cpus
def test_a_started_child_and_the_threads_it_makes_later_run_on_its_cpu() -> None:
    cpu = CPUS[-1]
    child = Child("sleeper", [sys.executable, "-c", LATE_THREAD], cpu=cpu)
    child.start()
    assert child.process is not None
    try:
        deadline = time.monotonic() + 10.0
        while len(_threads(child.process.pid)) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        threads = _threads(child.process.pid)
        assert len(threads) >= 2, "the child did not start its thread"
        assert {t: os.sched_getaffinity(t) for t in threads} == {t: {cpu} for t in threads}
    finally:
        child.process.kill()
        child.process.wait(timeout=10)


def test_a_cpu_the_system_refuses_leaves_the_process_running_unpinned(
    caplog: pytest.LogCaptureFixture,
) -> None:
    process = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        before = os.sched_getaffinity(process.pid)
        with caplog.at_level(logging.WARNING, logger="phalanx.up"):
            assert not pin_process(process.pid, 4095, "sleeper")  # (no such CPU here)
        assert "could not pin sleeper to CPU 4095" in caplog.text
        assert process.poll() is None
        assert os.sched_getaffinity(process.pid) == before
    finally:
        process.kill()
        process.wait(timeout=10)


def test_the_cli_takes_no_pin(tmp_path: Path) -> None:
    """`--no-pin` and `--pin` are options of `phalanx up` (its help lists them)."""
    done = subprocess.run(
        [sys.executable, "-m", "phalanx", "up", "--help"],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
        env={**os.environ, "COLUMNS": "200", "NO_COLOR": "1", "TERM": "dumb"},
        cwd=tmp_path,
    )
    assert "--pin" in done.stdout
    assert "--no-pin" in done.stdout
