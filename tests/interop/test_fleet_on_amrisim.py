"""The paper's wedge on three AMRISim P3DXs (firmware nobody here wrote), through the one
command a user runs: `phalanx up SCENARIO --robots amrisim`. Each robot's agent drives its
P3DX through the `arcos` driver over TCP, as it would a real one; the world process only
records, from AMRISim's true poses. The run must be whole, its commands must have reached
the robots, and the wedge must back out of its wall inside the bounds of perfect sensing;
a navigating wedge must get round a post to its goal on AMRISim's sonar.

Skipped unless PHALANX_AMRISIM gives the binary (docs/INTEROP.md)."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from phalanx.analysis.results import read_traces
from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.runtime.amrisim import AmrisimCommand, Xvfb, amrisim_map, free_port_run
from phalanx.wire.transport import free_tcp_port

pytestmark = [pytest.mark.integration, pytest.mark.drivers]
WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
# 60 s: the wall (the scenario's V, moved in) met at about 20 s, a 1.5 m reverse, on to the
# wall again and a second reverse before the end.
SHORT = [
    "duration_s=60",
    "deadlock.safe_distance_m=1.5",
    "world.polygons=[{vertices_m = [[4.0, 0.0], [2.6, 1.4], [2.7, 1.4], [4.1, 0.0], "
    "[2.7, -1.4], [2.6, -1.4]]}]",
]
# The field scenario with its field taken away, one post (radius 0.3 m) dead ahead on the
# leader's way and the goal 8 m off: the goal at 48.7 s on AMRISim (48.6 s in phalanx's
# simulator), 70 s of run.
FIELD = CONFIG_ROOT / "scenarios" / "nav_field_wedge3.toml"
POST_X_M, POST_RADIUS_M = 4.0, 0.3
POST = [
    "duration_s=70",
    "world.field.count=0",
    f"world.circles=[{{x_m = {POST_X_M}, y_m = 0.0, radius_m = {POST_RADIUS_M}}}]",
    "navigation.waypoints=[[8.0, 0.0]]",
]
# The targets of perfect sensing (docs/RESULTS.md), on AMRISim's true poses.
BACKWARD = {"linear_pct": 0.5, "angular_pct": 0.3, "orientation_deg": 0.5}


def _amrisim() -> Path:
    value = os.environ.get("PHALANX_AMRISIM")
    if not value:
        pytest.skip("PHALANX_AMRISIM is not set: give the AMRISim binary (docs/INTEROP.md)")
    if shutil.which("Xvfb") is None:
        pytest.skip("AMRISim needs an X display: install xvfb (apt-get install xvfb)")
    return Path(value)


def _commands_reached_the_robots(runtime: dict[str, Any], ticks: int) -> None:
    """Every step an agent ran sent its command to its robot; on the wall clock of a
    loaded machine an agent skips a step it cannot run in time rather than bunch steps up
    (`EpochClock`), a few in a run at most (CI runs at 1 cal = 27-46 ms: 29-77 of 1800).
    """
    agents = runtime["agents"]
    assert runtime["commands_expected"] == 3 * ticks
    assert runtime["commands_received"] == sum(a["commands_sent"] for a in agents.values())
    for report in agents.values():
        assert 0.95 * ticks <= report["commands_sent"] <= report["steps"] <= ticks, agents


def _up_on_amrisim(scenario: Path, sets: list[str], out: Path) -> subprocess.CompletedProcess[str]:
    """`phalanx up SCENARIO --robots amrisim` with `--set`s, its results in `out`: the
    finished command, which must have succeeded.
    """
    binary = _amrisim()
    overrides = [arg for s in sets for arg in ("--set", s)]
    proc = subprocess.run(
        [sys.executable, "-m", "phalanx", "up", str(scenario), "--robots", "amrisim",
         "--amrisim", str(binary), "--out", str(out), "--no-recording", "--timeout", "200",
         *overrides],
        capture_output=True, text=True, timeout=260, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


@pytest.mark.timeout(300)
def test_the_wedge_backs_out_of_its_wall_in_formation_on_amrisim(tmp_path: Path) -> None:
    out = tmp_path / "amrisim"
    proc = _up_on_amrisim(WEDGE, SHORT, out)
    # Robots leave as their run ends: that is said, and no robot is called lost.
    assert "is gone" not in proc.stderr, proc.stderr[-3000:]
    assert proc.stderr.count("has left, its run done") == 3, proc.stderr[-3000:]
    # Each robot is placed where the scenario starts it, said as SIM_SET_POSE has it.
    start = load_scenario(WEDGE).start_pose("r2")
    x_mm, y_mm = round(start.x_m * 1000), round(start.y_m * 1000)
    placed = f"({x_mm} mm, {y_mm} mm, {round(math.degrees(start.theta_rad))} deg)"
    assert f"r2 INFO placed the robot at {placed} (SIM_SET_POSE)" in proc.stderr, proc.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["complete"], metrics["incomplete_reason"]
    assert set(metrics["pose_source"].values()) == {"simulator's true pose (AMRISim SIMSTAT)"}
    _commands_reached_the_robots(metrics["runtime"], 600)
    assert metrics["deadlock_reverses"] >= 1
    assert metrics["collisions"] == []
    for rid in ("r2", "r3"):
        backward = metrics["followers"][rid]["backward"]
        assert backward["samples"] > 40, backward
        for key, bound in BACKWARD.items():
            assert backward[key]["max"] < bound, (rid, key, backward[key])
    traces = read_traces(out / "traces.npz")
    moved = np.hypot(np.diff(traces["r1"]["x_m"]), np.diff(traces["r1"]["y_m"])).sum()
    assert moved > 5.0  # it drove (4 m out, 1.5 m back, on, back): not a robot standing still
    assert (out / "fig5_trajectories.png").stat().st_size > 10_000
    assert "Loading map data" in (out / "amrisim.log").read_text(errors="replace")


@pytest.mark.timeout(300)
def test_a_navigating_wedge_goes_round_a_post_on_amrisims_sonar(tmp_path: Path) -> None:
    """A navigating wedge (the field scenario with one post dead ahead on the way to
    its goal) maps, plans and steers on the echoes AMRISim's P3DXs send, its own sonar
    model, not phalanx's: it gets round the post to the goal with no contact."""
    out = tmp_path / "amrisim"
    _up_on_amrisim(FIELD, POST, out)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["complete"], metrics["incomplete_reason"]
    assert set(metrics["pose_source"].values()) == {"simulator's true pose (AMRISim SIMSTAT)"}
    _commands_reached_the_robots(metrics["runtime"], 700)
    navigation = metrics["navigation"]
    assert navigation["goal_reached"], navigation["stuck_reason"]
    assert navigation["collisions_obstacle"] == navigation["collisions_robot"] == 0
    assert metrics["collisions"] == []
    # the leader turned off the straight line to the goal to pass the post
    traces = read_traces(out / "traces.npz")
    beside = np.abs(traces["r1"]["x_m"] - POST_X_M) < 0.3
    assert beside.any(), traces["r1"]["x_m"].max()
    assert np.abs(traces["r1"]["y_m"][beside]).min() > POST_RADIUS_M


@pytest.mark.timeout(300)
def test_a_lab_deployment_without_a_world_writes_its_results(tmp_path: Path) -> None:
    """configs/deployments/amrisim.toml: a host per robot, each robot on the arcos driver,
    no [world] (a lab's layout), launched with `phalanx launch --local` against a running
    AMRISim. The world process runs on the first host and simulates nothing: it records
    the robots from their true poses and writes the results folder."""
    binary = _amrisim()
    scenario = load_scenario(WEDGE)
    base = free_port_run(3)
    command = AmrisimCommand(binary, tmp_path / "amrisim.map", tmp_path / "amrisim.log", base)
    command.map_path.write_text(amrisim_map(scenario))
    example = (CONFIG_ROOT / "deployments" / "amrisim.toml").read_text()
    text = example.replace("../scenarios/paper_wedge.toml", str(WEDGE))
    for i in range(3):
        text = text.replace(f"127.0.0.1:810{i + 1}", f"127.0.0.1:{base + i}")
    for i in range(4):
        text = text.replace(f"port = 746{i + 1}", f"port = {free_tcp_port()}")
    deployment = tmp_path / "amrisim.toml"
    deployment.write_text(text)
    with Xvfb() as display:
        simulator = subprocess.Popen(
            command.argv(scenario), env=command.env(display.display), start_new_session=True,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            proc = subprocess.run(
                [sys.executable, "-m", "phalanx", "launch", str(deployment), "--local",
                 "--run-id", "lab1", "--no-table", "--set", "duration_s=25"],
                cwd=tmp_path, capture_output=True, text=True, timeout=240, check=False,
            )  # fmt: skip
        finally:
            simulator.kill()
            simulator.wait(10.0)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    results = tmp_path / "results" / "deployments" / "lab1"
    metrics = json.loads((results / "metrics.json").read_text())
    assert metrics["complete"], metrics["incomplete_reason"]
    assert set(metrics["pose_source"].values()) == {"simulator's true pose (AMRISim SIMSTAT)"}
    _commands_reached_the_robots(metrics["runtime"], 250)
    start = scenario.start_pose("r2")
    traces = read_traces(results / "traces.npz")
    # placed at its start pose (SIM_SET_POSE), then off into the wedge
    assert (traces["r2"]["x_m"][0], traces["r2"]["y_m"][0]) == pytest.approx(
        (start.x_m, start.y_m), abs=0.02
    )
    assert traces["r1"]["x_m"][-1] > 3.0
