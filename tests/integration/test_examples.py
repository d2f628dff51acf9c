"""Every file of examples/ does what its header says: each scenario runs end to end (cut
short) by the command in its header and shows what it is there to show, the scripts run
a scenario through the library and plot its results folder, every TOML file passes
`phalanx validate`, every other command a header gives parses, the map is the floor plan
of its scenario's world, and no file of examples/ goes untested or unlisted.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import typer
from matplotlib.path import Path as Outline
from typer.testing import CliRunner

from phalanx.analysis.report import worst
from phalanx.cli import app
from phalanx.core.mapfile import OCCUPIED, load_map

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "examples"
README = EXAMPLES / "README.md"
LABELLED = re.compile(r"^# ([^:]+): (phalanx .*)$")


def _goal_reached(metrics: dict[str, Any]) -> None:
    assert metrics["navigation"]["goal_reached"], metrics["navigation"]


def _own_shape(metrics: dict[str, Any]) -> None:
    assert set(metrics["followers"]) == {"r2", "r3", "r4"}
    assert all(f["forward"]["samples"] > 200 for f in metrics["followers"].values())
    assert worst(metrics, "forward", "linear_pct") < 5.0


def _waypoints(metrics: dict[str, Any]) -> None:
    _goal_reached(metrics)
    # round the table in the wedge: no fold into a column
    assert metrics["navigation"]["reshapes"] == 0
    assert metrics["navigation"]["scenario_shape_share"] > 0.9


def _field(metrics: dict[str, Any]) -> None:
    assert metrics["navigation"]["collisions_obstacle"] == 0
    assert metrics["navigation"]["episode_share"] < 0.5


def _deadlock(metrics: dict[str, Any]) -> None:
    assert metrics["deadlock_reverses"] == 1
    assert all(f["backward"]["samples"] > 100 for f in metrics["followers"].values())
    assert worst(metrics, "backward", "linear_pct") < 0.5  # the formation core's bound
    assert worst(metrics, "backward", "orientation_deg") < 0.5


def _mocap(metrics: dict[str, Any]) -> None:
    robots = metrics["estimation"]["robots"]
    assert set(robots) == {"r1", "r2", "r3"}
    assert all(r["position_m"]["max"] < 0.01 for r in robots.values())


# Each scenario example: how long the test runs it (s, cut short of its own duration) and
# what its run must show. A run is deterministic, so these hold on any machine.
SCENARIOS: dict[str, tuple[float, Callable[[dict[str, Any]], None]]] = {
    "scenarios/own_shape.toml": (40.0, _own_shape),
    "scenarios/own_robot.toml": (60.0, _goal_reached),  # the goal at 48.7 s
    "scenarios/waypoints.toml": (125.0, _waypoints),  # the last waypoint at 113.4 s
    "scenarios/known_map.toml": (75.0, _goal_reached),  # through the door by 66.5 s
    "scenarios/obstacle_field.toml": (40.0, _field),
    "scenarios/deadlock_escape.toml": (120.0, _deadlock),  # backed out by 113.5 s
    "scenarios/mocap.toml": (30.0, _mocap),
}
VALIDATED = [
    "robots/small_robot.toml",
    "deployments/two_hosts.toml",
    "deployments/p3dx_serial.toml",
    "deployments/amrisim.toml",
]
SCRIPTS = ["scripts/run_scenario.py", "scripts/plot_results.py"]
MAP = ["maps/office.yaml", "maps/office.pgm"]  # read by known_map.toml's run
TOML = [*SCENARIOS, *VALIDATED]


def _example_files() -> set[str]:
    return {
        p.relative_to(EXAMPLES).as_posix()
        for p in EXAMPLES.rglob("*")
        if p.is_file() and "__pycache__" not in p.parts
    }


def _header(path: Path) -> list[str]:
    """The comment lines a TOML file starts with, lines continued by a backslash joined."""
    lines: list[str] = []
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line.startswith("#"):
            break
        if lines and lines[-1].endswith("\\"):
            lines[-1] = lines[-1][:-1].rstrip() + " " + line.lstrip("# ")
        else:
            lines.append(line.rstrip())
    return lines


def _commands(name: str) -> dict[str, list[list[str]]]:
    """The `# Label: phalanx ...` commands of an example's header, by label."""
    found: dict[str, list[list[str]]] = {}
    for line in _header(EXAMPLES / name):
        match = LABELLED.match(line)
        if match:
            found.setdefault(match.group(1), []).append(shlex.split(match.group(2))[1:])
    return found


def _invoke(args: list[str]) -> Any:
    return CliRunner().invoke(app, args, prog_name="phalanx")


def _parses(words: list[str]) -> None:
    """Put `phalanx WORDS` through the option parsers of its verb (and sub-verb), as the
    shell would hand it over, without running it: unknown verbs, unknown options and
    missing values raise."""
    command: Any = typer.main.get_command(app)
    ctx = command.context_class(command, info_name="phalanx", **command.context_settings)
    args = list(words)
    while True:
        _, rest, _ = command.make_parser(ctx).parse_args(args=args)
        if not hasattr(command, "get_command"):
            assert not rest, f"phalanx {shlex.join(words)}: unexpected {rest}"
            return
        verb, args = rest[0], rest[1:]
        sub = command.get_command(ctx, verb)
        assert sub is not None, f"phalanx {shlex.join(words)}: no verb {verb!r}"
        command = sub
        ctx = command.context_class(command, info_name=verb, parent=ctx, **command.context_settings)


def test_every_example_is_tested_and_listed() -> None:
    tested = {*SCENARIOS, *VALIDATED, *SCRIPTS, *MAP, "README.md"}
    files = _example_files()
    assert files - tested == set(), "examples no test covers: add them to this file"
    assert tested - files == set(), "examples this file names that are gone"
    readme = README.read_text(encoding="utf-8")
    unlisted = sorted(f for f in files - {"README.md"} if f"({f})" not in readme)
    assert not unlisted, f"examples/README.md does not link {unlisted}"


def test_every_toml_example_validates(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)  # scenarios name their robot file and map from the root
    paths = [f"examples/{name}" for name in TOML]
    result = _invoke(["validate", *paths])
    assert result.exit_code == 0, result.output
    assert [line.split(":")[0] for line in result.output.splitlines()] == paths
    readme = README.read_text(encoding="utf-8")
    for name in VALIDATED:  # each one's header says how to check it, and how to run it
        commands = _commands(name)
        assert commands["Check"] == [["validate", f"examples/{name}"]]
        for run in commands.get("Run", []):
            assert f"`phalanx {shlex.join(run)}`" in readme


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_scenario_example_runs_by_its_header(
    name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(REPO)
    (run,) = _commands(name)["Run"]
    assert run == ["run", f"examples/{name}"]
    assert f"`phalanx {shlex.join(run)}`" in README.read_text(encoding="utf-8")
    duration_s, check = SCENARIOS[name]
    short = ["--set", f"duration_s={duration_s}", "--no-figures", "--no-recording"]
    result = _invoke([*run, *short, "--no-progress", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    metrics = json.loads((tmp_path / "metrics.json").read_text(encoding="utf-8"))
    assert metrics["duration_s"] == duration_s
    assert not metrics["collisions"]
    check(metrics)


def test_every_other_header_command_parses() -> None:
    """What the tests do not run (a deployment's launch, its hosts, certificates, the
    motion-capture bridge) is at least a command phalanx takes."""
    others = [
        words
        for name in TOML
        for label, commands in _commands(name).items()
        if label != "Check" and not (label == "Run" and name in SCENARIOS)
        for words in commands
    ]
    assert {words[0] for words in others} >= {"launch", "host", "pki", "mocap", "up", "view"}
    for words in others:
        _parses(words)


def test_the_map_is_the_floor_plan_of_its_world() -> None:
    scenario = tomllib.loads((EXAMPLES / "scenarios/known_map.toml").read_text(encoding="utf-8"))
    assert scenario["navigation"]["prior_map"] == "examples/maps/office.yaml"
    plan = load_map(EXAMPLES / "maps/office.yaml")
    walls = [Outline(p["vertices_m"]) for p in scenario["world"]["polygons"]]
    x, y = plan.centres(OCCUPIED)
    centres = np.column_stack([x, y])
    inside = np.zeros(len(centres), dtype=bool)
    for wall in walls:
        held = wall.contains_points(centres, radius=1e-9)
        assert held.sum() > 10  # every wall is on the plan ...
        inside |= held
    assert inside.all()  # ... and nothing else is
    door = (x > 4.9) & (x < 5.3) & (y > 2.05) & (y < 4.75)
    assert not door.any()


@pytest.mark.timeout(180)  # its child processes' own bound, and set-up
def test_the_scripts_run_a_scenario_and_plot_its_results(tmp_path: Path) -> None:
    out = tmp_path / "api"
    ran = subprocess.run(
        [sys.executable, "examples/scripts/run_scenario.py", "examples/scenarios/own_shape.toml",
         "--duration-s", "30", "--out", str(out)],
        cwd=REPO, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert ran.returncode == 0, ran.stderr
    metrics = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    assert metrics["duration_s"] == 30.0
    r4 = metrics["followers"]["r4"]["forward"]["linear_pct"]["max"]
    assert f"r4 forward : linear {r4:.3g} %" in ran.stdout
    png = tmp_path / "separations.png"
    plotted = subprocess.run(
        [sys.executable, "examples/scripts/plot_results.py", str(out), "--out", str(png)],
        cwd=REPO, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert plotted.returncode == 0, plotted.stderr
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert png.stat().st_size > 10_000
    readme = README.read_text(encoding="utf-8")
    for script in SCRIPTS:
        doc = (EXAMPLES / script).read_text(encoding="utf-8").split('"""')[1]
        assert f".venv/bin/python examples/{script}" in doc
        assert f"`.venv/bin/python examples/{script}" in readme
