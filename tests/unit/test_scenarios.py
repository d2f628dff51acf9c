"""Navigation scenarios: the files match their generator, fields are seeded, shapes."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from phalanx.core.config import Scenario as ScenarioModel
from phalanx.core.config_files import CONFIG_ROOT, load_scenario, validate_data
from phalanx.core.formation import resolve_formation
from phalanx.core.scenarios import (
    COURSES,
    SHAPES,
    formation_shape,
    navigation_scenario,
    obstacle_field,
    resolve_world,
    scenario_toml,
)

NAV_FILES = sorted((CONFIG_ROOT / "scenarios").glob("nav_*.toml"))


def test_a_file_for_every_course_shape_and_size() -> None:
    names = {p.stem for p in NAV_FILES}
    assert names == {f"nav_{c}_{s}{n}" for c in COURSES for s in SHAPES for n in (3, 5)}


@pytest.mark.parametrize("path", NAV_FILES, ids=[p.stem for p in NAV_FILES])
def test_files_match_the_generator(path: Path) -> None:
    _, course, rest = path.stem.split("_")
    shape, n = rest[:-1], int(rest[-1])
    seed = 1 if course == "field" else 0
    assert load_scenario(path) == navigation_scenario(course, shape, n, seed=seed)  # type: ignore[arg-type]


def test_toml_round_trip() -> None:
    scenario = navigation_scenario("field", "wedge", 5, seed=3)
    import tomllib

    back = validate_data(ScenarioModel, tomllib.loads(scenario_toml(scenario)), source="t")
    assert back == scenario


def test_field_is_seeded_keeps_clear_and_apart() -> None:
    scenario = navigation_scenario("field", "collateral", 3, seed=11)
    field = scenario.world.field
    assert field is not None
    a, b = obstacle_field(field), obstacle_field(field)
    assert a == b
    assert len(a) == field.count
    other = obstacle_field(field.model_copy(update={"seed": 12}))
    assert other != a
    for i, c in enumerate(a):
        for zone in field.keep_clear:
            assert math.hypot(c.x_m - zone.x_m, c.y_m - zone.y_m) > c.radius_m + zone.radius_m
        for d in a[i + 1 :]:
            gap = math.hypot(c.x_m - d.x_m, c.y_m - d.y_m) - c.radius_m - d.radius_m
            assert gap >= field.min_gap_m - 1e-9
    resolved = resolve_world(scenario.world)
    assert resolved.field is None
    assert len(resolved.circles) == field.count


@pytest.mark.parametrize("shape", SHAPES)
def test_shapes_space_neighbours_one_metre_apart(shape: str) -> None:
    formation = resolve_formation(formation_shape(shape, 5))  # type: ignore[arg-type]
    for rid, parent in formation.parents.items():
        if parent is not None:
            assert formation.polar_of(rid, parent)[0] == pytest.approx(1.0)
    assert formation.root == "r1"
