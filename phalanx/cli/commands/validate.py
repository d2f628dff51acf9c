"""`phalanx validate`: check scenario, deployment and robot files with the loaders `run`
and `launch` use, and print the JSON Schema of each kind of file (docs/schema/).
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import typer

from phalanx.cli.style import choice

if TYPE_CHECKING:
    from pydantic import BaseModel

Kind = Literal["scenario", "deployment", "robot"]
KINDS: tuple[Kind, ...] = ("scenario", "deployment", "robot")
SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"
# Keys only a deployment file has at its top level (a scenario has none of them).
_DEPLOYMENT_KEYS = frozenset({"fleet", "hosts"})


def validate(
    files: Annotated[
        list[Path] | None,
        typer.Argument(
            metavar="FILE", help="Scenario, deployment or robot files (TOML; JSON is read too)."
        ),
    ] = None,
    schema: Annotated[
        str | None,
        typer.Option(
            "--schema",
            metavar="scenario|deployment|robot",
            help="Print the JSON Schema of this kind of file instead of checking files.",
        ),
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option("--out", "-o", help="Write the schema to this file.", dir_okay=False),
    ] = None,
) -> None:
    """Check each FILE as what it holds (a scenario, a deployment or a robot file, told
    apart by its keys) with the loaders of `run` and `launch`; print one line per file and
    exit 2 if any is invalid. With --schema, print the JSON Schema editors can check files
    against (the committed copies are in docs/schema/).
    """
    if schema is not None:
        if files:
            raise typer.BadParameter("give files to check or --schema, not both")
        _write_schema(_kind(schema), out)
        return
    if out is not None:
        raise typer.BadParameter("--out goes with --schema", param_hint="'--out'")
    if not files:
        raise typer.BadParameter("give at least one file, or --schema KIND", param_hint="FILES")
    failed = [path for path in files if not _check(path)]
    if failed:
        raise typer.Exit(2)


def _kind(name: str) -> Kind:
    choice(name, KINDS, option="--schema")
    return next(kind for kind in KINDS if kind == name)


def schema_model(kind: Kind) -> type[BaseModel]:
    """The pydantic model that a file of this kind is."""
    if kind == "deployment":
        from phalanx.hosts.deployment import Deployment

        return Deployment
    if kind == "robot":
        from phalanx.core.robot_params import RobotParams

        return RobotParams
    from phalanx.core.config import Scenario

    return Scenario


def schema_text(kind: Kind) -> str:
    """The JSON Schema of a `kind` file, as committed in docs/schema/KIND.schema.json."""
    generated = schema_model(kind).model_json_schema()
    document = {"$schema": SCHEMA_DIALECT, **generated}
    return json.dumps(document, indent=2, allow_nan=False) + "\n"


def _write_schema(kind: Kind, out: Path | None) -> None:
    text = schema_text(kind)
    if out is None:
        typer.echo(text, nl=False)
        return
    from phalanx.core.errors import ConfigError

    try:
        out.write_text(text, encoding="utf-8")
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{out}: cannot write the schema: {exc}") from exc
    typer.echo(f"schema: {out}", err=True)


def file_kind(path: Path) -> Kind:
    """What a file holds, told by its top-level keys: a deployment (`fleet`, `hosts`), a
    robot file (only robot parameters) or, otherwise, a scenario (whose loader reports
    what is wrong with anything else).
    """
    from phalanx.core.config_files import holds_robot_params, read_text
    from phalanx.core.errors import ConfigError

    try:
        text = read_text(path)
        data: Any = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
    except (ConfigError, ValueError, RecursionError):  # the loader says what is wrong
        return "scenario"
    if not isinstance(data, dict):
        return "scenario"
    if _DEPLOYMENT_KEYS & set(data):
        return "deployment"
    return "robot" if holds_robot_params(data) else "scenario"


def describe(path: Path) -> str:
    """What a valid file is ("scenario 'x', 3 robots"); ConfigError if it is not valid."""
    from phalanx.core.config_files import load_scenario, validate_file

    kind = file_kind(path)
    if kind == "deployment":
        from phalanx.hosts.deployment import load_deployment

        loaded = load_deployment(path)
        spec = loaded.spec
        return (
            f"deployment {spec.name!r}, {len(spec.hosts)} hosts, {len(spec.robots)} robots, "
            f"scenario {loaded.scenario.name!r}"
        )
    if kind == "robot":
        from phalanx.core.robot_params import RobotParams

        robot = validate_file(RobotParams, path)
        return f"robot {robot.name!r}"
    scenario = load_scenario(path)
    return f"scenario {scenario.name!r}, {len(scenario.robots)} robots"


def _check(path: Path) -> bool:
    from phalanx.core.errors import PhalanxError

    try:
        summary = describe(path)
    except PhalanxError as exc:
        typer.echo(f"error: {exc}", err=True)
        return False
    typer.echo(f"{path}: ok ({summary})")
    return True


def register(app: typer.Typer) -> None:
    """Add `phalanx validate`."""
    app.command("validate")(validate)
