"""Every number a user's file holds is bounded both ways: each field of a scenario, a
deployment, a robot file, a camera calibration, a robot driver's settings (a
deployment's `[robots.driver]`), an agent's spec and a host daemon's status, as its JSON
Schema states it (the schema is pydantic's own account of the model's constraints). A
new field declared as a bare `float` or `int` fails here, before a file can put 1e300
in it.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from pydantic import BaseModel, ValidationError

from phalanx.cli.commands.validate import KINDS, schema_model
from phalanx.core.config import Scenario
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.localisation import CameraCalibration
from phalanx.core.quantities import MAX_EXTENT_M, MAX_SPEED_MPS
from phalanx.drivers.arcos_settings import ArcosSettings
from phalanx.drivers.canopen import CanopenSettings
from phalanx.hosts.protocol import ChildStatus
from phalanx.runtime.process_spec import AgentSpec

MODELS: dict[str, type[BaseModel]] = {
    **{kind: schema_model(kind) for kind in KINDS},
    "camera": CameraCalibration,
    "arcos driver": ArcosSettings,
    "canopen driver": CanopenSettings,
    "agent spec": AgentSpec,
    "host status": ChildStatus,
}


def _numbers(
    node: dict[str, Any], defs: dict[str, Any], path: str, seen: frozenset[str]
) -> Iterator[tuple[str, dict[str, Any]]]:
    """Every number or integer of a JSON Schema node, with its path (each `$defs` entry
    followed once along a path).
    """
    ref = node.get("$ref")
    if ref is not None:
        name = ref.rsplit("/", 1)[-1]
        if name not in seen:
            yield from _numbers(defs[name], defs, path, seen | {name})
        return
    for key in ("anyOf", "oneOf", "allOf"):
        for sub in node.get(key, ()):
            yield from _numbers(sub, defs, path, seen)
    if node.get("type") in ("number", "integer"):
        yield path, node
    for name, sub in node.get("properties", {}).items():
        yield from _numbers(sub, defs, f"{path}.{name}", seen)
    for key in ("items", "additionalProperties"):
        sub = node.get(key)
        if isinstance(sub, dict):
            yield from _numbers(sub, defs, f"{path}[]", seen)
    for i, sub in enumerate(node.get("prefixItems", ())):
        yield from _numbers(sub, defs, f"{path}[{i}]", seen)


def _bounds(model: type[BaseModel]) -> dict[str, dict[str, Any]]:
    """Every number of `model`'s JSON Schema by its path."""
    schema = model.model_json_schema()
    return dict(_numbers(schema, schema.get("$defs", {}), "", frozenset()))


def _bounded(node: dict[str, Any]) -> bool:
    """A number with a lower and an upper bound, or one of a few values."""
    if {"enum", "const"} & node.keys():
        return True
    low = {"minimum", "exclusiveMinimum"} & node.keys()
    return bool(low) and bool({"maximum", "exclusiveMaximum"} & node.keys())


def _unbounded(model: type[BaseModel]) -> list[str]:
    return [path for path, node in _bounds(model).items() if not _bounded(node)]


@pytest.mark.parametrize("kind", sorted(MODELS))
def test_every_number_of_a_file_is_bounded_both_ways(kind: str) -> None:
    model = MODELS[kind]
    assert len(_bounds(model)) >= 4  # (the walk reaches the model's numbers at all)
    assert _unbounded(model) == []


def test_a_bare_float_field_is_caught() -> None:
    class Loose(BaseModel):
        x_m: float
        n: int = 0

    assert _unbounded(Loose) == [".x_m", ".n"]


def test_the_bounds_are_where_the_shipped_files_are_not() -> None:
    """The shipped files sit well inside the bounds, and a value past one is refused
    with the field's name.
    """
    scenario = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
    robot = load_robot("p3dx")
    assert robot.v_max_mps < MAX_SPEED_MPS
    data = scenario.model_dump()
    data["robots"][0]["start"]["x_m"] = 2 * MAX_EXTENT_M
    with pytest.raises(ValidationError, match=r"robots\.0\.start\.x_m"):
        Scenario.model_validate(data)
    data = scenario.model_dump()
    data["duration_s"] = scenario.dt_s / 2
    with pytest.raises(ValidationError, match="shorter than one control period"):
        Scenario.model_validate(data)
    data["duration_s"] = scenario.dt_s
    assert Scenario.model_validate(data).duration_s == scenario.dt_s


@pytest.mark.parametrize("sign", [0, 10, -2])
def test_a_drives_mounting_sign_is_one_either_way(sign: int) -> None:
    # (a sign of 10 commanded the drive ten times the wheel speed asked for, 0 none)
    with pytest.raises(ValidationError, match="left_sign"):
        CanopenSettings(left_sign=sign)  # type: ignore[arg-type]
    assert CanopenSettings(left_sign=-1).left_sign == -1


def test_an_agents_watchdog_is_a_safety_stop_never_long() -> None:
    spec = {"scenario": "s.toml", "robot_id": "r1"}
    assert AgentSpec.model_validate({**spec, "watchdog_s": 10.0}).watchdog_s == 10.0
    with pytest.raises(ValidationError, match="watchdog_s"):
        AgentSpec.model_validate({**spec, "watchdog_s": 3600.0})
