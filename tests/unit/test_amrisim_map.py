"""A scenario's world as an AMRISim map (ARIA's map format): its walls and circles as
wall lines in millimetres, never smaller than the obstacle; a map without walls has no
line count (ARIA's reader refuses "NumLines: 0"); the robots wait parked clear of it,
on the ports AMRISim gives them in the order of their names."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.core.errors import ConfigError
from phalanx.runtime.amrisim import (
    AmrisimCommand,
    amrisim_binary,
    amrisim_map,
    amrisim_ports,
    odometry_error,
    parking,
)

SCENARIOS = CONFIG_ROOT / "scenarios"


def _lines(text: str) -> list[tuple[int, int, int, int]]:
    rows = text.split("LINES\n", 1)[1].split("DATA", 1)[0].split()
    values = [int(v) for v in rows]
    return [
        (values[i], values[i + 1], values[i + 2], values[i + 3]) for i in range(0, len(values), 4)
    ]


def test_the_papers_wall_becomes_wall_lines_in_millimetres() -> None:
    text = amrisim_map(load_scenario(SCENARIOS / "paper_collateral.toml"))
    assert text.startswith("2D-Map\n")
    assert "NumLines: 4" in text
    assert sorted(_lines(text)) == sorted([
        (12000, 4130, 12100, 4130), (12100, 4130, 12100, 7330),
        (12100, 7330, 12000, 7330), (12000, 7330, 12000, 4130),
    ])  # fmt: skip


def test_a_circle_is_drawn_round_it_never_inside() -> None:
    scenario = load_scenario(SCENARIOS / "nav_corridor_wedge3.toml")
    circle = scenario.world.circles[0]
    reach_m = 2 * circle.radius_m
    lines = _lines(amrisim_map(scenario))
    near = [
        a for a in lines if math.hypot(a[0] / 1e3 - circle.x_m, a[1] / 1e3 - circle.y_m) < reach_m
    ]
    assert len(near) >= 32
    for ax, ay, bx, by in near:  # each side's nearest point to the centre is on the circle
        mx, my = (ax + bx) / 2000, (ay + by) / 2000
        assert math.hypot(mx - circle.x_m, my - circle.y_m) == pytest.approx(
            circle.radius_m, abs=0.002
        )


def test_a_map_without_walls_has_no_line_count_and_bounds_the_parking_row() -> None:
    scenario = load_scenario(SCENARIOS / "paper_wedge.toml").model_copy(
        update={"world": load_scenario(SCENARIOS / "paper_wedge.toml").world.model_copy(
            update={"polygons": ()})}
    )  # fmt: skip
    text = amrisim_map(scenario)
    assert "NumLines" not in text
    assert "LINES" not in text
    x_m, y_m = parking(scenario)
    assert x_m > max(r.start.x_m for r in scenario.robots) + 10.0
    low = text.split("MinPos: ")[1].split("\n")[0].split()
    high = text.split("MaxPos: ")[1].split("\n")[0].split()
    assert int(low[1]) < (y_m - len(scenario.robots)) * 1000 < int(high[1])
    assert int(low[0]) < x_m * 1000 < int(high[0])


def test_ports_follow_the_robots_names_and_the_command_line_parks_them(tmp_path: Path) -> None:
    assert amrisim_ports(("r3", "r1", "r10", "r2"), 9000) == {
        "r1": 9000, "r10": 9001, "r2": 9002, "r3": 9003,
    }  # fmt: skip
    scenario = load_scenario(SCENARIOS / "paper_wedge.toml")
    binary = tmp_path / "AMRISim"
    command = AmrisimCommand(binary, tmp_path / "m.map", tmp_path / "a.log", base_port=9100)
    argv = command.argv(scenario)
    assert argv[argv.index("-p") + 1] == "9100"
    assert [argv[i + 1] for i, a in enumerate(argv) if a == "-r"] == [
        "p3dx:r1",
        "p3dx:r2",
        "p3dx:r3",
    ]
    assert argv[argv.index("--bind-to-address") + 1] == "127.0.0.1"
    assert argv[argv.index("--start") + 1] == f"{round(parking(scenario)[0] * 1000)},0,0"
    assert command.env(":7")["AMRISIM"] == str(tmp_path)


def test_a_missing_binary_or_mode_says_what_to_give(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("PHALANX_AMRISIM", raising=False)
    with pytest.raises(ConfigError, match="PHALANX_AMRISIM"):
        amrisim_binary(None)
    with pytest.raises(ConfigError, match="no such executable"):
        amrisim_binary(tmp_path / "nowhere")
    with pytest.raises(ConfigError, match="random_init"):
        odometry_error("sometimes")
    assert odometry_error("none") == "none"


def test_up_without_amrisim_says_how_to_get_it(tmp_path: Path) -> None:
    """The one command on a machine without AMRISim: one clear message, exit 2, nothing
    started (no process is left: the fixture checks)."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "PHALANX_AMRISIM"}
    argv = [sys.executable, "-m", "phalanx", "up", str(SCENARIOS / "paper_wedge.toml"),
            "--robots", "amrisim", "--out", str(tmp_path / "out")]  # fmt: skip
    missing = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=60, check=False)
    assert missing.returncode == 2
    assert "PHALANX_AMRISIM" in missing.stderr
    assert "docs/INTEROP.md" in missing.stderr
    wrong = subprocess.run(
        [*argv, "--amrisim", str(tmp_path / "AMRISim")],
        env=env, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert wrong.returncode == 2
    assert "no such executable" in wrong.stderr
    mode = subprocess.run(
        [*argv, "--amrisim-odometry-error", "often"],
        env=env, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert mode.returncode == 2
    assert "random_each_update" in mode.stderr
