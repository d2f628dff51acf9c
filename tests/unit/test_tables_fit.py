"""Every table a command prints fits the terminal: at 80 and at 200 columns no line is
longer, side by side when the columns fit and a `field: value` block per row when they
do not; plain text (no Markdown pipes) unless Markdown is asked; never `nan`. The
Markdown written into docs/ is built apart and does not change."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from phalanx.analysis import paired
from phalanx.analysis import sweep as sw
from phalanx.analysis.metrics import run_metrics
from phalanx.analysis.report import (
    Case,
    matrix_cells,
    matrix_rows,
    print_summary,
    text_table,
)
from phalanx.cli import app
from phalanx.cli.commands.deploy import STATUS_HEADERS, status_cells
from phalanx.cli.tables import markdown_cells
from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_scenario
from phalanx.hosts.fleet_output import Row
from phalanx.runtime.batch import run_batch

WIDTHS = (80, 200)
SCENARIOS = CONFIG_ROOT / "scenarios"


@pytest.fixture(scope="module")
def wedge_metrics() -> dict[str, Any]:
    """A short paper wedge: no reverse yet, so its backward phase has nothing (NaN)."""
    scenario = apply_overrides(load_scenario(SCENARIOS / "paper_wedge.toml"), ["duration_s=20"])
    return run_metrics(run_batch(scenario))


@pytest.fixture(scope="module")
def sweep_rows() -> list[dict[str, Any]]:
    """Two short sweep runs of one group (real runs, as `phalanx sweep` makes them)."""
    return [
        json.loads(json.dumps(sw.run_job(job), allow_nan=True))
        for job in sw.jobs(["field"], ["inline"], [3], [0, 1], overrides=[("duration_s", 8.0)])
    ]


def _fits(lines: list[str], width: int) -> None:
    text = "\n".join(lines)
    assert max(len(line) for line in lines) <= width, text
    assert "nan" not in text.lower(), text
    assert "|" not in text, text


@pytest.mark.parametrize("width", WIDTHS)
def test_the_run_summary_fits(wedge_metrics: dict[str, Any], width: int) -> None:
    out = io.StringIO()
    print_summary(wedge_metrics, width=width, stream=out)
    lines = out.getvalue().splitlines()
    _fits(lines, width)
    assert lines[0] == "paper-wedge / ours"
    # 8 columns fit in 80: side by side, the phase never run shown as dashes
    assert any(line.startswith("r2") and "backward" in line and " - " in line for line in lines)


@pytest.mark.parametrize("width", WIDTHS)
def test_the_report_matrix_fits(wedge_metrics: dict[str, Any], width: int) -> None:
    cases = [Case("wedge", "ours"), Case("wedge", "ours", noise=True)]
    headers, rows = matrix_cells(cases, [wedge_metrics, wedge_metrics])
    lines = text_table(headers, rows, width=width, title="the matrix")
    _fits(lines, width)
    vertical = any(line.startswith("formation:") for line in lines)
    assert vertical == (width == 80)  # ten columns: a block per case in 80 columns
    assert "ours + noise" in "\n".join(lines)
    # RESULTS.md's rows are as they were: Markdown, `nan` where the docs have it
    assert matrix_rows(cases, [wedge_metrics] * 2)[0].startswith("| wedge | ours | n/a |")


@pytest.mark.parametrize("width", WIDTHS)
def test_the_sweep_table_has_a_terminal_form(sweep_rows: list[dict[str, Any]], width: int) -> None:
    groups = sw.summaries(sweep_rows)
    lines = sw.terminal_table(groups, width=width)
    _fits(lines, width)
    blocks = [line for line in lines if line.startswith("family:")]
    assert len(blocks) == (1 if width == 80 else 0)  # 19 columns: a block in 80
    if width == 200:
        assert lines[1 + lines.index(next(x for x in lines if x.startswith("-")))].startswith(
            "field"
        )


def test_the_sweep_markdown_is_what_results_md_holds(sweep_rows: list[dict[str, Any]]) -> None:
    groups = sw.summaries(sweep_rows)
    asked = sw.terminal_table(groups, width=80, markdown=True)
    written = sw.table(groups)
    assert [line for line in asked if line.startswith("| ")] == [written[0], *written[2:]]
    assert written[0].count("|") == len(sw.TABLE_HEADERS) + 1


@pytest.mark.parametrize("width", WIDTHS)
def test_the_sweep_comparison_fits(sweep_rows: list[dict[str, Any]], width: int) -> None:
    before = paired.Sweep(
        runs={(sw.group_key(r), r["job"]["seed"]): _run(r) for r in sweep_rows}, skipped=0
    )
    pairs = paired.compare(before, before)
    headers, rows = markdown_cells(paired.table(pairs))
    assert len(headers) == 13
    assert len(rows) == 1
    lines = text_table(headers, rows, width=width, title="a -> b")
    _fits(lines, width)


def _run(row: dict[str, Any]) -> paired.Run:
    ratio = row["time_to_goal_s"] / row["route_s"] if row["goal_reached"] else None
    return paired.Run(row["goal_reached"], ratio, row["deadlock_reverses"], row["episode_share"])


@pytest.mark.parametrize("width", WIDTHS)
def test_the_status_table_fits(width: int) -> None:
    rows = [
        Row("r1", "robot-a", "running", 0, "NAVIGATE", "r1", 10.0, "", 0, 0),
        Row("r2", "robot-b", "backoff", 3, "-", "-", None,
            "exited with code 1: " + "a long last error " * 8, None, None),
        Row("world", "laptop", "running", 0, "tick 120/2000", "-", None, "", 2, 1),
    ]  # fmt: skip
    lines = text_table(STATUS_HEADERS, status_cells(rows), width=width, title="loopback")
    _fits(lines, width)


def test_a_nan_anywhere_is_a_dash_and_markdown_only_when_asked() -> None:
    rows = [["r1", math.nan, "nan -> 0.5", "0.1"], ["r2", None, "1.0", "nan"]]
    plain = text_table(["robot", "a", "b", "c"], rows, width=80)
    assert "nan" not in "\n".join(plain).lower()
    assert plain[-1].split() == ["r2", "-", "1.0", "-"]
    asked = text_table(["robot", "a", "b", "c"], rows, width=80, markdown=True)
    assert asked[0] == "| robot | a | b | c |"
    assert asked[2] == "| r1 | - | - -> 0.5 | 0.1 |"


def test_a_value_too_long_for_any_layout_is_wrapped_within_the_width() -> None:
    long = "x" * 150
    for width in WIDTHS:
        lines = text_table(["field", "a rather long header of a field"], [["a", long]], width=width)
        assert max(len(line) for line in lines) <= width
        assert "".join(lines).count("x") == 150


def test_run_prints_its_table_plain_in_a_pipe(tmp_path: Path) -> None:
    result = CliRunner().invoke(
        app,
        ["run", str(SCENARIOS / "paper_wedge.toml"), "--set", "duration_s=2", "--no-figures",
         "--no-recording", "--no-progress", "--out", str(tmp_path / "out")],
        env={"COLUMNS": None},
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    *lines, results = result.output.splitlines()
    _fits(lines, 80)  # (the last line names the results folder, as long as its path)
    assert results == f"results: {tmp_path / 'out'}"
    assert not any(set(line) & set("│┃━─") for line in lines)  # no box drawing either
