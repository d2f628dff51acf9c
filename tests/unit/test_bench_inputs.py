"""The benchmarks' own inputs stay valid as the code they measure changes: the latency
benchmarks' fleet (`bench_zenoh_latency.fleet_scenario`, which `bench_step_cold.py`
steps in one process) is a scenario the file checks accept, and its follower steps on
both sonar readings. (A bound on `leader_timeout_s` once made both scripts stop at
their first line.)"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def bench_path() -> Iterator[None]:
    """The benchmarks' folder first on the import path (their `calibration` helper)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.syspath_prepend(str(REPO / "bench"))
        yield
    for name in ("bench_step_cold", "bench_zenoh_latency", "calibration"):
        sys.modules.pop(name, None)


@pytest.mark.parametrize("robots", [10, 30])
def test_the_latency_fleet_is_a_valid_scenario_no_leader_times_out_in(
    bench_path: None, robots: int
) -> None:
    import bench_zenoh_latency

    scenario = bench_zenoh_latency.fleet_scenario(robots)
    assert len(scenario.robots) == robots
    assert scenario.leader_timeout_s >= 3600.0  # far past any benchmark's run


@pytest.mark.parametrize("sonar", ["open", "formation"])
def test_the_cold_step_benchmark_steps_its_follower(bench_path: None, sonar: str) -> None:
    import bench_step_cold

    step = bench_step_cold.follower(sonar)
    times_s = [step(k) for k in range(5)]
    assert all(0.0 < t < 10.0 for t in times_s), times_s
