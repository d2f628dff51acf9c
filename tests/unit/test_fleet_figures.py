"""Figures of a large fleet are drawn as collections, and the figure step can be skipped;
a dead end's drawing says when there was no reverse."""

from __future__ import annotations

from pathlib import Path

import pytest
from matplotlib.collections import LineCollection

from phalanx.analysis import figures
from phalanx.analysis.plotting import LEGEND_MAX, POINTS_PER_LINE, decimated
from phalanx.analysis.results import write_results
from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.core.runlog import RunLog
from phalanx.core.scenarios import grid_scenario
from phalanx.runtime.batch import run_batch


@pytest.fixture(scope="module")
def fleet_log() -> RunLog:
    base = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
    return run_batch(grid_scenario(base, LEGEND_MAX + 4, duration_s=3.0))


@pytest.mark.parametrize("name", sorted(figures.FIGURES))
def test_a_fleet_is_drawn_as_collections_without_a_legend_entry_each(
    fleet_log: RunLog, name: str
) -> None:
    fig = figures.FIGURES[name](fleet_log)
    try:
        main = fig.axes[0]
        lines = [c for c in main.collections if isinstance(c, LineCollection)]
        assert lines, "the robots' lines should be one collection"
        assert sum(len(c.get_segments()) for c in lines) >= len(fleet_log.traces) - 1
        assert main.get_legend() is None
        assert len(main.get_lines()) <= 4  # bounds and the like, not a line per robot
    finally:
        figures.plt.close(fig)


def test_long_lines_are_decimated_to_about_the_points_drawn() -> None:
    n = 5 * POINTS_PER_LINE + 3
    xs = [float(i) for i in range(n)]
    kept = decimated(xs, xs)  # type: ignore[arg-type]
    assert len(kept) <= POINTS_PER_LINE + 1
    assert kept[0, 0] == 0.0  # the ends stay
    assert kept[-1, 0] == n - 1


def test_results_without_figures_write_metrics_only(fleet_log: RunLog, tmp_path: Path) -> None:
    metrics = write_results(fleet_log, tmp_path, recording=False, figures=False)
    assert (tmp_path / "metrics.json").exists()
    assert not list(tmp_path.glob("*.png"))
    assert metrics["followers"]


def test_a_dead_end_drawing_of_a_group_that_never_reversed_says_so(fleet_log: RunLog) -> None:
    # (the fleet's 3 s go forwards only: no reverse to draw the errors of)
    fig = figures.deadend_escape(fleet_log)
    try:
        ax_map, ax_err = fig.axes[:2]
        assert ax_map.get_title().endswith("round, no reverse")
        assert [t.get_text() for t in ax_err.texts if t.get_text() == "no reverse"]
    finally:
        figures.plt.close(fig)
