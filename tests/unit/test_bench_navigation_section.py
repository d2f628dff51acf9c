"""`bench/bench_montecarlo.py --write` puts back what docs/RESULTS.md's navigation section
holds: the dead end's table, its notes and figures, and no table of the seeded fields
(the sweep's section holds theirs). The section's own numbers, fed back to the
generator, give the section byte for byte."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from phalanx.analysis.metrics import CORE_BOUNDS
from phalanx.analysis.report import SECTION_BEGIN, SECTION_END, section_of

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "docs" / "RESULTS.md"


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    with pytest.MonkeyPatch.context() as patch:
        patch.syspath_prepend(str(REPO / "bench"))  # (its `calibration` helper)
        spec = importlib.util.spec_from_file_location(
            "bench_montecarlo", REPO / "bench" / "bench_montecarlo.py"
        )
        assert spec is not None
        assert spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module


def _cells(line: str) -> list[str]:
    return [cell.strip() for cell in line.strip().strip("|").split("|")]


def _result(line: str) -> dict[str, Any]:
    """A dead end's result as `deadend_run` gives it, read back from its table row."""
    shape, robots, reverses, measured, *errors, stood, goal, collisions = _cells(line)
    reached = goal.startswith("yes")
    return {
        "shape": shape,
        "robots": int(robots),
        "deadlock_reverses": int(reverses),
        "backward_s": float(measured.removesuffix(" s")) if measured[0].isdigit() else 0.0,
        "worst": {
            key: 0.0 if cell == "-" else float(cell.split()[0])
            for key, cell in zip(CORE_BOUNDS, errors, strict=True)
        },
        "stood_s": [] if stood == "-" else [float(x.split()[0]) for x in stood.split(" / ")],
        "goal_reached": reached,
        "time_to_goal_s": float(goal.split("(")[1].split()[0]) if reached else math.nan,
        "collisions_obstacle": int(collisions),
        "collisions_robot": 0,
    }


def test_the_section_written_is_the_one_in_the_docs(bench: ModuleType) -> None:
    current = section_of(RESULTS.read_text(encoding="utf-8"))
    assert current.startswith(SECTION_BEGIN)
    assert current.endswith(SECTION_END)
    rows = [line for line in current.splitlines() if line.startswith("| ") and "---" not in line]
    header, *body = rows
    assert _cells(header)[:2] == ["formation", "robots"]
    assert len(body) == 6  # three shapes, of three and of five robots
    assert bench.section([_result(line) for line in body]) == current


def test_the_section_has_no_field_table_and_names_its_figures(bench: ModuleType) -> None:
    result = _result("| wedge | 3 | 1 | 62 s | 0.0149 ✓ | 0.00175 ✓ | 0.7 ✗ | 9.5 s | no | 0 |")
    written = bench.section([result])
    assert "| family |" not in written
    assert "| formation | runs |" not in written  # the seeded fields' table of old
    assert "0.7 ✗" in written  # above the core bound of orientation (0.5 deg)
    for name, _, _ in bench.DEADEND_FIGURES:
        assert f"(figures/{name})" in written
        assert (REPO / "docs" / "figures" / name).is_file()


def test_a_group_that_never_reversed_shows_dashes_and_why(bench: ModuleType) -> None:
    never = "| inline | 3 | 0 | none (no dead end called) | - | - | - | - | yes (103 s) | 0 |"
    row = _result(never)
    (line,) = [x for x in bench.deadend_table([row]) if x.startswith("| inline")]
    assert "| none (no dead end called) | - | - | - | - | yes (103 s) |" in line
    assert "nan" not in line
