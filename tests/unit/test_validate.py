"""`phalanx validate`: every shipped configuration file checks out, each file is told
apart by its content, wrong files give the loaders' message and exit 2, and the JSON
Schemas committed in docs/schema/ are the ones the models generate today.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from phalanx.cli import app
from phalanx.cli.commands.validate import KINDS, Kind, file_kind, schema_model, schema_text

REPO = Path(__file__).resolve().parents[2]
CONFIGS = REPO / "configs"
SCHEMAS = REPO / "docs" / "schema"
SHIPPED: dict[Kind, list[Path]] = {
    "scenario": sorted((CONFIGS / "scenarios").glob("*.toml")),
    "deployment": sorted((CONFIGS / "deployments").glob("*.toml")),
    "robot": sorted((CONFIGS / "robots").glob("*.toml")),
}
ROBOT = CONFIGS / "robots" / "p3dx.toml"
SCENARIO = CONFIGS / "scenarios" / "paper_wedge.toml"


def _invoke(*args: str) -> Any:
    return CliRunner().invoke(app, ["validate", *args], prog_name="phalanx")


@pytest.mark.parametrize("kind", KINDS)
def test_committed_schema_is_current(kind: Kind) -> None:
    committed = (SCHEMAS / f"{kind}.schema.json").read_text(encoding="utf-8")
    assert committed == schema_text(kind), (
        f"docs/schema/{kind}.schema.json is stale: run "
        f"phalanx validate --schema {kind} -o docs/schema/{kind}.schema.json"
    )


@pytest.mark.timeout(180)  # its child processes' own bound, and set-up
def test_every_shipped_file_validates_in_one_call() -> None:
    files = [path for paths in SHIPPED.values() for path in paths]
    assert all(SHIPPED.values()), SHIPPED
    done = subprocess.run(
        [sys.executable, "-m", "phalanx", "validate", *map(str, files)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert len(lines) == len(files)
    assert f"{SCENARIO}: ok (scenario 'paper-wedge', 3 robots)" in lines
    assert f"{ROBOT}: ok (robot 'p3dx')" in lines
    assert any(": ok (deployment 'loopback', 3 hosts, 3 robots" in line for line in lines)


@pytest.mark.parametrize("kind", KINDS)
def test_shipped_files_are_told_apart_and_fit_their_schema(kind: Kind) -> None:
    """No `jsonschema` package here: each file is checked against its model, and its
    top-level keys against the schema's properties and required fields.
    """
    import tomllib

    schema = json.loads((SCHEMAS / f"{kind}.schema.json").read_text(encoding="utf-8"))
    assert schema["additionalProperties"] is False
    for path in SHIPPED[kind]:
        assert file_kind(path) == kind, path
        data = tomllib.loads(path.read_text(encoding="utf-8"))
        assert set(data) <= set(schema["properties"]), path
        assert set(schema.get("required", ())) <= set(data), path
        schema_model(kind).model_validate(data)


def test_wrong_files_give_the_loaders_message_and_exit_2(tmp_path: Path) -> None:
    misspelt = tmp_path / "misspelt.toml"
    misspelt.write_text(SCENARIO.read_text(encoding="utf-8").replace("duration_s", "duraton_s"))
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"\xff\xfe\x00junk")
    deployment = tmp_path / "deployment.toml"
    text = (CONFIGS / "deployments" / "loopback.toml").read_text(encoding="utf-8")
    scenario_line = 'scenario = "../scenarios/paper_wedge.toml"'
    assert scenario_line in text
    deployment.write_text(
        text.replace(scenario_line, f'scenario = "{SCENARIO}"').replace(
            'host = "robot-a"', 'host = "robot-c"', 1
        )
    )
    result = _invoke(str(SCENARIO), str(misspelt), str(binary), str(deployment))
    assert result.exit_code == 2
    assert f"{SCENARIO}: ok (scenario 'paper-wedge', 3 robots)" in result.stdout
    errors = result.stderr
    assert f"{misspelt}: invalid Scenario" in errors
    assert "(did you mean 'duration_s'?)" in errors
    assert f"{binary}: not a text file" in errors
    assert f"{deployment}: invalid Deployment" in errors
    assert "'robot-c' is not in hosts" in errors
    assert "Traceback" not in result.output


def test_a_robot_file_is_checked_as_one(tmp_path: Path) -> None:
    wrong = tmp_path / "robot.toml"
    wrong.write_text(ROBOT.read_text(encoding="utf-8").replace("radius_m = 0.25", "radius_m = -1"))
    assert file_kind(wrong) == "robot"
    result = _invoke(str(wrong))
    assert result.exit_code == 2
    assert f"{wrong}: invalid RobotParams" in result.stderr
    assert "radius_m" in result.stderr


def test_a_schema_line_for_editors_is_only_a_comment(tmp_path: Path) -> None:
    marked = tmp_path / "marked.toml"
    marked.write_text(
        f"#:schema {SCHEMAS / 'scenario.schema.json'}\n" + SCENARIO.read_text(encoding="utf-8")
    )
    result = _invoke(str(marked))
    assert result.exit_code == 0, result.output
    assert f"{marked}: ok (scenario 'paper-wedge', 3 robots)" in result.stdout


def test_schema_is_printed_and_written(tmp_path: Path) -> None:
    printed = _invoke("--schema", "deployment")
    assert printed.exit_code == 0, printed.output
    document = json.loads(printed.stdout)
    assert document["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert document["title"] == "Deployment"
    out = tmp_path / "robot.schema.json"
    written = _invoke("--schema", "robot", "-o", str(out))
    assert written.exit_code == 0, written.output
    assert out.read_text(encoding="utf-8") == schema_text("robot")


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["--schema", "robt"], "'robt' is not one of scenario, deployment, robot"),
        (["--schema", "robot", str(ROBOT)], "not both"),
        ([], "give at least one file"),
        (["-o", "x.json", str(ROBOT)], "--out goes with --schema"),
    ],
)
def test_usage_mistakes_exit_2_with_a_message(args: list[str], said: str) -> None:
    result = _invoke(*args)
    assert result.exit_code == 2
    assert said in result.output
