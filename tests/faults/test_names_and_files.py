"""Names that cannot escape, seeds numpy takes, files read only where they are named.

A scenario's `name` becomes a folder (`results/<name>-<controller>`), its `seed` feeds
numpy's generators, its `robot` names a robot file: each is checked when the file
loads, so a hostile value ends `phalanx run` with exit 2 and one message naming the
field, never a traceback, a folder outside `results/` or a file read from elsewhere.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
from fleetlab import CLI, WEDGE

from phalanx.core.config_files import CONFIG_ROOT, ROBOTS_DIR, load_robot, load_scenario
from phalanx.core.errors import ConfigError
from phalanx.hosts.deployment import load_deployment

WEDGE_TEXT = WEDGE.read_text()
FIELD = CONFIG_ROOT / "scenarios" / "nav_field_wedge3.toml"
QUICK = ["--no-recording", "--no-figures", "--no-progress", "--set", "duration_s=1"]


def _run(scenario: Path, *extra: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    argv = [*CLI, "run", str(scenario), *QUICK, *extra]
    return subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=cwd, check=False)


def _refused(proc: subprocess.CompletedProcess[str], *says: str) -> None:
    assert proc.returncode == 2, proc.stdout[-1000:] + proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr + proc.stdout
    for text in says:
        assert text in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) <= 4, proc.stderr


def _with_name(name: str) -> str:
    return re.sub(r'(?m)^name = ".*"$', f'name = "{name}"', WEDGE_TEXT, count=1)


def _files_under(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file())


# --- a scenario's name --------------------------------------------------------------------


@pytest.mark.parametrize("name", ["../../escaped", "ABSOLUTE", "", "..", "a/b", "-x"])
def test_a_name_that_is_a_path_is_refused_and_nothing_written(tmp_path: Path, name: str) -> None:
    name = name.replace("ABSOLUTE", str(tmp_path / "absolute"))
    cwd = tmp_path / "a" / "b"
    cwd.mkdir(parents=True)
    scenario = tmp_path / "named.toml"
    scenario.write_text(_with_name(name))
    _refused(_run(scenario, cwd=cwd), str(scenario), "name:", "expected a name")
    assert _files_under(tmp_path) == [scenario]  # no results anywhere, inside or out


@pytest.mark.timeout(180)  # its child processes' own bound, and set-up
def test_up_refuses_a_name_that_is_a_path_before_starting_anything(tmp_path: Path) -> None:
    scenario = tmp_path / "named.toml"
    scenario.write_text(_with_name(str(tmp_path / "absolute")))
    argv = [*CLI, "up", str(scenario), "--fleet", "names47", "--timeout", "60",
            "--no-recording", "--set", "duration_s=1"]  # fmt: skip
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=tmp_path,
                          check=False)  # fmt: skip
    _refused(proc, str(scenario), "name:")
    assert "recording:" not in proc.stdout  # nothing started
    assert _files_under(tmp_path) == [scenario]


def test_a_name_set_on_the_command_line_is_checked_too(tmp_path: Path) -> None:
    outside = tmp_path / "outside"
    proc = _run(WEDGE, "--set", f'name="{outside}"', cwd=tmp_path)
    _refused(proc, "name:", "--set")
    assert _files_under(tmp_path) == []


def test_every_name_in_configs_is_a_name(tmp_path: Path) -> None:
    proc = _run(WEDGE, "--set", 'name="paper-wedge.v2_1"', cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "results" / "paper-wedge.v2_1-ours" / "metrics.json").is_file()
    for path in sorted((CONFIG_ROOT / "scenarios").glob("*.toml")):
        load_scenario(path)
    for path in sorted((CONFIG_ROOT / "deployments").glob("*.toml")):
        load_deployment(path)


# --- seeds ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("scenario", "assignment", "field"),
    [
        (WEDGE, "seed=-1", "seed:"),
        (WEDGE, f"seed={2**63}", "seed:"),
        (FIELD, "world.field.seed=-1", "world.field.seed:"),
    ],
)
def test_a_seed_numpy_cannot_take_is_one_message(
    tmp_path: Path, scenario: Path, assignment: str, field: str
) -> None:
    _refused(_run(scenario, "--set", assignment, cwd=tmp_path), field, str(scenario))


def test_a_negative_seed_in_the_file_is_one_message(tmp_path: Path) -> None:
    scenario = tmp_path / "seeded.toml"
    scenario.write_text(WEDGE_TEXT.replace("seed = 1", "seed = -1", 1))
    _refused(_run(scenario, cwd=tmp_path), str(scenario), "seed:", "greater than or equal to 0")


# --- deep nesting ---------------------------------------------------------------------------

DEPTH = 5000


@pytest.mark.parametrize(
    "nested",
    [
        "x = " + "[" * DEPTH + "]" * DEPTH + "\n",
        "x = " + "{a = " * DEPTH + "1" + "}" * DEPTH + "\n",
        "[" + ".".join(["a"] * DEPTH) + "]\nb = 1\n",
    ],
    ids=["arrays", "inline tables", "dotted tables"],
)
def test_a_deeply_nested_file_is_called_too_deep(tmp_path: Path, nested: str) -> None:
    scenario = tmp_path / "deep.toml"
    scenario.write_text(WEDGE_TEXT + "\n" + nested)
    proc = _run(scenario, cwd=tmp_path)
    _refused(proc, str(scenario), "nested too deeply")
    assert "JSON" not in proc.stderr


def test_a_deeply_nested_json_file_is_called_too_deep(tmp_path: Path) -> None:
    scenario = tmp_path / "deep.json"
    scenario.write_text('{"name": "deep", "x": ' + "[" * DEPTH + "]" * DEPTH + "}")
    _refused(_run(scenario, cwd=tmp_path), str(scenario), "nested too deeply")


def test_a_deeply_nested_set_value_is_called_too_deep(tmp_path: Path) -> None:
    proc = _run(WEDGE, "--set", "seed=" + "[" * DEPTH, cwd=tmp_path)
    _refused(proc, "--set seed", "nested too deeply")


# --- robot files ----------------------------------------------------------------------------


def test_a_robot_that_is_a_path_without_its_extension_is_refused(tmp_path: Path) -> None:
    scenario = tmp_path / "passwd.toml"
    scenario.write_text(WEDGE_TEXT.replace('robot = "p3dx"', 'robot = "/etc/passwd"', 1))
    proc = _run(scenario, cwd=tmp_path)
    _refused(proc, str(scenario), "robot:", "'/etc/passwd'")
    assert "/etc/passwd.toml" not in proc.stderr  # no file looked for


def test_load_robot_never_adds_an_extension_to_a_path(tmp_path: Path) -> None:
    elsewhere = tmp_path / "elsewhere.toml"
    elsewhere.write_text((ROBOTS_DIR / "p3dx.toml").read_text())
    with pytest.raises(ConfigError, match="robot: expected a robot's name"):
        load_robot(str(tmp_path / "elsewhere"))
    with pytest.raises(ConfigError, match="robot: expected a robot's name"):
        load_robot("../robots/p3dx")
    assert load_robot(elsewhere) == load_robot("p3dx")  # an explicit .toml path is read
    assert load_robot(str(elsewhere)).name == "p3dx"


def test_a_robot_file_given_by_its_path_still_runs(tmp_path: Path) -> None:
    robot = tmp_path / "mine.toml"
    robot.write_text((ROBOTS_DIR / "p3dx.toml").read_text())
    scenario = tmp_path / "mine_robot.toml"
    scenario.write_text(WEDGE_TEXT.replace('robot = "p3dx"', f'robot = "{robot}"', 1))
    proc = _run(scenario, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_a_nul_in_a_robot_path_is_one_message(tmp_path: Path) -> None:
    scenario = tmp_path / "nul.toml"
    scenario.write_text(WEDGE_TEXT.replace('robot = "p3dx"', 'robot = "a\\u0000.toml"', 1))
    _refused(_run(scenario, cwd=tmp_path), str(scenario), "robot:", "control characters")
    with pytest.raises(ConfigError, match="control characters"):
        load_robot("a\x00.toml")
