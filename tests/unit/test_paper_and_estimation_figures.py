"""The combined paper figure (the paper's figures 4b, 5, 6 and 7 as the four panels of one
PDF, `paper.pdf`, written with a run's other figures) and the estimation figure of a run
with the pose estimator on (`estimation.png`: the estimate against ground truth over
time, with the covariance's bounds and the NEES band)."""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterator
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.figure import Figure, FigureBase
from typer.testing import CliRunner

from phalanx.analysis import figures
from phalanx.analysis.estimation import estimation_metrics
from phalanx.analysis.results import read_run_traces, read_traces, write_results, write_traces
from phalanx.cli import app
from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_scenario
from phalanx.core.runlog import RunLog
from phalanx.runtime.batch import run_batch

SCENARIOS = CONFIG_ROOT / "scenarios"


@pytest.fixture(scope="module")
def wedge() -> RunLog:
    return run_batch(load_scenario(SCENARIOS / "paper_wedge.toml"))


@pytest.fixture(scope="module")
def estimated() -> RunLog:
    """The real-sensing wedge, past its settling time (30 s)."""
    scenario = load_scenario(SCENARIOS / "real_wedge.toml")
    return run_batch(apply_overrides(scenario, ["duration_s=45"]))


@pytest.fixture
def paper(wedge: RunLog) -> Iterator[Figure]:
    fig = figures.paper_figure(wedge)
    fig.canvas.draw()
    yield fig
    plt.close(fig)


def _outside(fig: FigureBase, renderer: object) -> None:
    """Every legend of `fig` lies outside every axes of the whole figure."""
    legends = list(fig.legends)
    for legend in legends:
        box = legend.get_window_extent(renderer)
        for ax in fig.get_figure(root=True).axes:
            area = ax.get_window_extent(renderer)
            overlap_x = min(box.x1, area.x1) - max(box.x0, area.x0)
            overlap_y = min(box.y1, area.y1) - max(box.y0, area.y0)
            assert overlap_x <= 0 or overlap_y <= 0, (legend, ax.get_title())


def test_the_paper_figure_has_the_four_panels_in_the_papers_order(paper: Figure) -> None:
    panels = paper.subfigs
    assert len(panels) == 4
    titles = [" ".join(ax.get_title() for ax in panel.axes) for panel in panels]
    for title, (label, words) in zip(
        titles,
        [("(a) fig. 4b", "behaviour states"), ("(b) fig. 5", "trajectories"),
         ("(c) fig. 6", "separations"), ("(d) fig. 7", "velocity profiles")],
        strict=True,
    ):  # fmt: skip
        assert title.startswith(label), title
        assert words in title
    assert [len(panel.axes) for panel in panels] == [2, 1, 2, 2]
    suptitle = paper.get_suptitle()
    assert suptitle == "paper-wedge / ours"  # the scenario and the controller, once
    renderer = paper.canvas.get_renderer()  # type: ignore[attr-defined]
    for panel in panels:
        assert len(panel.legends) == 1  # each panel's key, right of it
        _outside(panel, renderer)


def test_the_trajectories_panel_keeps_equal_aspect(paper: Figure) -> None:
    (ax,) = paper.subfigs[1].axes
    assert ax.get_aspect() == 1.0


def _pdf_pages(data: bytes) -> int:
    """The pages of a PDF matplotlib wrote (its page objects are not compressed)."""
    return len(re.findall(rb"/Type\s*/Page(?!s)", data))


def test_a_run_writes_paper_pdf_one_page_beside_its_figures(wedge: RunLog, tmp_path: Path) -> None:
    write_results(wedge, tmp_path, recording=False)
    data = (tmp_path / figures.PAPER_FIGURE).read_bytes()
    assert data.startswith(b"%PDF-")
    assert b"%%EOF" in data[-64:]
    assert _pdf_pages(data) == 1
    for name in figures.FIGURES:
        assert (tmp_path / name).is_file()
    assert not (tmp_path / figures.ESTIMATION_FIGURE).exists()  # no estimator in this run


def test_paper_pdf_can_be_left_out(wedge: RunLog, tmp_path: Path) -> None:
    write_results(wedge, tmp_path, recording=False, paper=False)
    assert not (tmp_path / figures.PAPER_FIGURE).exists()
    write_results(wedge, tmp_path / "bare", recording=False, figures=False)
    assert not (tmp_path / "bare" / figures.PAPER_FIGURE).exists()


def test_the_estimation_figure_shows_estimate_covariance_and_nees(estimated: RunLog) -> None:
    assert figures.has_estimates(estimated)
    fig = figures.estimation(estimated)
    try:
        fig.canvas.draw()
        ax_p, ax_h, ax_n = fig.axes
        assert estimated.scenario.name in ax_p.get_title()
        assert str(estimated.scenario.controller.kind) in ax_p.get_title()
        assert "mm" in ax_p.get_ylabel()
        assert "heading" in ax_h.get_ylabel()
        assert len(ax_h.collections) == len(estimated.traces)  # a 2-sigma band each
        assert ax_n.get_yscale() == "log"
        robots = sorted(estimated.traces)
        keys = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
        assert [k.split()[0] for k in keys[: len(robots)]] == robots
        assert all("% in band" in k for k in keys[: len(robots)])
        assert "NEES 95 % band" in keys
        # an estimate line and a 2-sigma line per robot on the position panel
        assert len(ax_p.get_lines()) >= 2 * len(robots)
        low, high = ax_p.get_ylim()
        assert low == 0.0
        assert high < 20.0  # fitted to the settled run (mm), not to the start's covariance
        _outside(fig, fig.canvas.get_renderer())  # type: ignore[attr-defined]
    finally:
        plt.close(fig)


def test_a_run_without_the_estimator_has_no_estimation_figure(wedge: RunLog) -> None:
    assert not figures.has_estimates(wedge)


def test_phalanx_run_writes_the_estimation_figure_for_a_real_scenario(tmp_path: Path) -> None:
    args = ["run", str(SCENARIOS / "real_wedge.toml"), "--set", "duration_s=35", "-o",
            str(tmp_path), "--no-recording", "--no-progress"]  # fmt: skip
    result = CliRunner().invoke(app, args, prog_name="phalanx")
    assert result.exit_code == 0, result.output
    png = (tmp_path / figures.ESTIMATION_FIGURE).read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / figures.PAPER_FIGURE).is_file()


def test_traces_keep_the_estimates_and_give_back_the_same_honesty(
    estimated: RunLog, wedge: RunLog, tmp_path: Path
) -> None:
    # (what a run on robots is judged by afterwards: the estimate beside the truth)
    write_traces(estimated, tmp_path / "traces.npz")
    t_s, traces = read_run_traces(tmp_path / "traces.npz")
    for rid, trace in estimated.traces.items():
        np.testing.assert_array_equal(traces[rid].estimate, trace.estimate)
        np.testing.assert_array_equal(traces[rid].cov, trace.cov)
    again = dataclasses.replace(estimated, t_s=t_s, traces=traces)
    assert estimation_metrics(again) == estimation_metrics(estimated)
    write_traces(wedge, tmp_path / "paper.npz")  # no estimator: no estimate kept
    assert "estimate" not in read_traces(tmp_path / "paper.npz")["r2"]


def test_traces_with_an_estimate_no_run_writes_are_refused(
    estimated: RunLog, tmp_path: Path
) -> None:
    write_traces(estimated, tmp_path / "traces.npz")
    arrays = dict(np.load(tmp_path / "traces.npz"))
    for key, value, says in (
        ("r2/cov", np.full_like(arrays["r2/cov"], np.inf), "r2/cov: values beyond"),
        ("r2/estimate", arrays["r2/estimate"][:, :2], "rows of 3"),
    ):
        spoilt = {**arrays, key: value}
        np.savez_compressed(tmp_path / "spoilt.npz", **spoilt)
        with pytest.raises(ValueError, match=says):
            read_run_traces(tmp_path / "spoilt.npz")
