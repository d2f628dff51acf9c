"""Figures fit for a paper: PNG, PDF or SVG at a chosen pixel density, legends outside
the data, a line style per robot, titles naming the scenario and the controller."""

from __future__ import annotations

import struct
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path

import matplotlib.pyplot as plt
import pytest
from matplotlib.figure import Figure
from matplotlib.legend import Legend
from typer.testing import CliRunner

from phalanx.analysis import figures
from phalanx.analysis.figures import STATE_ROWS
from phalanx.cli import app
from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.core.runlog import RunLog
from phalanx.core.states import State
from phalanx.runtime.batch import run_batch

SCENARIOS = ("paper_wedge", "paper_inline")
WITH_LEGENDS = ("fig5_trajectories.png", "fig6_separations.png", "fig7_velocities.png")


@pytest.fixture(scope="module")
def logs() -> dict[str, RunLog]:
    return {
        name: run_batch(load_scenario(CONFIG_ROOT / "scenarios" / f"{name}.toml"))
        for name in SCENARIOS
    }


@pytest.fixture
def drawn(logs: dict[str, RunLog], request: pytest.FixtureRequest) -> Iterator[Figure]:
    scenario, name = request.param
    fig = figures.FIGURES[name](logs[scenario])
    fig.canvas.draw()
    yield fig
    plt.close(fig)


CASES = [(s, n) for s in SCENARIOS for n in WITH_LEGENDS]


def _png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = struct.unpack(">II", head[16:24])
    return width, height


def test_pdf_figures_are_pdf_files(logs: dict[str, RunLog], tmp_path: Path) -> None:
    written = figures.write_figures(logs["paper_wedge"], tmp_path, fmt="pdf")
    assert sorted(p.name for p in written) == sorted(
        figures.figure_name(n, "pdf") for n in figures.FIGURES
    )
    for path in written:
        data = path.read_bytes()
        assert data.startswith(b"%PDF-")
        assert b"%%EOF" in data[-64:]


def test_svg_figures_parse_as_svg(logs: dict[str, RunLog], tmp_path: Path) -> None:
    written = figures.write_figures(logs["paper_inline"], tmp_path, fmt="svg")
    assert len(written) == len(figures.FIGURES)
    for path in written:
        assert path.suffix == ".svg"
        root = ET.parse(path).getroot()  # noqa: S314 - our own output
        assert root.tag == "{http://www.w3.org/2000/svg}svg"


def test_dpi_sets_the_png_pixel_size(logs: dict[str, RunLog], tmp_path: Path) -> None:
    log = logs["paper_wedge"]
    low = figures.write_figures(log, tmp_path / "low", dpi=60)
    high = figures.write_figures(log, tmp_path / "high", dpi=120)
    for a, b in zip(low, high, strict=True):
        (wa, ha), (wb, hb) = _png_size(a), _png_size(b)
        assert wb == pytest.approx(2 * wa, abs=2)
        assert hb == pytest.approx(2 * ha, abs=2)


def test_the_default_dpi_is_150(logs: dict[str, RunLog], tmp_path: Path) -> None:
    fig = figures.FIGURES["fig7_velocities.png"](logs["paper_wedge"])
    inches = fig.get_size_inches()
    (path,) = [
        p for p in figures.write_figures(logs["paper_wedge"], tmp_path) if p.stem.startswith("fig7")
    ]
    plt.close(fig)
    assert _png_size(path) == pytest.approx((150 * inches[0], 150 * inches[1]), abs=2)


@pytest.mark.parametrize("drawn", CASES, indirect=True, ids=[f"{s}-{n}" for s, n in CASES])
def test_every_legend_lies_outside_every_axes(drawn: Figure) -> None:
    legends: list[Legend] = list(drawn.legends)
    legends += [leg for ax in drawn.axes if (leg := ax.get_legend()) is not None]
    assert legends, "a figure of three robots has a legend"
    renderer = drawn.canvas.get_renderer()  # type: ignore[attr-defined]
    for legend in legends:
        box = legend.get_window_extent(renderer)
        for ax in drawn.axes:
            area = ax.get_window_extent(renderer)
            overlap_x = min(box.x1, area.x1) - max(box.x0, area.x0)
            overlap_y = min(box.y1, area.y1) - max(box.y0, area.y0)
            assert overlap_x <= 0 or overlap_y <= 0, (box, area)


@pytest.mark.parametrize("drawn", CASES, indirect=True, ids=[f"{s}-{n}" for s, n in CASES])
def test_titles_name_the_scenario_and_the_controller(
    drawn: Figure, logs: dict[str, RunLog], request: pytest.FixtureRequest
) -> None:
    scenario = logs[request.node.callspec.params["drawn"][0]].scenario
    titles = " ".join(ax.get_title() for ax in drawn.axes)
    assert scenario.name in titles
    assert str(scenario.controller.kind) in titles


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_every_robot_path_has_a_line_style_of_its_own(
    logs: dict[str, RunLog], scenario: str
) -> None:
    log = logs[scenario]
    fig = figures.trajectories(log)
    try:
        (ax,) = fig.axes
        styles = {
            str(line.get_label()): str(line.get_linestyle())
            for line in ax.get_lines()
            if line.get_label() in log.traces
        }
        assert sorted(styles) == sorted(log.traces)
        assert len(set(styles.values())) == len(styles)
        assert "o start" not in ax.get_title()
        keys = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
        assert "circle: start" in keys
        assert "square: end" in keys
    finally:
        plt.close(fig)


def test_reverse_is_drawn_apart_from_forward(logs: dict[str, RunLog]) -> None:
    """The reverse phase is a wide pale band under the path, not a line on top of it."""
    fig = figures.trajectories(logs["paper_wedge"])
    try:
        (ax,) = fig.axes
        paths = [line for line in ax.get_lines() if line.get_label() in {"r1", "r2", "r3"}]
        bands = [line for line in ax.get_lines() if line.get_alpha() is not None]
        assert len(bands) == len(paths) == 3
        assert min(b.get_linewidth() for b in bands) > 2 * max(p.get_linewidth() for p in paths)
    finally:
        plt.close(fig)


def test_the_trajectories_axes_fit_the_course_at_equal_aspect(logs: dict[str, RunLog]) -> None:
    """A course wider than tall gets a figure wider than tall, with little white space."""
    log = logs["paper_inline"]
    fig = figures.trajectories(log)
    try:
        fig.canvas.draw()
        (ax,) = fig.axes
        assert ax.get_aspect() == 1.0
        x0, x1 = ax.get_xlim()
        y0, y1 = ax.get_ylim()
        for tr in log.traces.values():
            assert x0 <= float(tr.x_m.min())
            assert float(tr.x_m.max()) <= x1
            assert y0 <= float(tr.y_m.min())
            assert float(tr.y_m.max()) <= y1
        box = ax.get_window_extent()
        width, height = fig.get_size_inches() * fig.dpi
        assert box.width * box.height > 0.45 * width * height
    finally:
        plt.close(fig)


def test_run_writes_svg_figures_when_asked(tmp_path: Path) -> None:
    scenario = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
    args = ["run", str(scenario), "-o", str(tmp_path), "--format", "svg", "--no-recording"]
    result = CliRunner().invoke(app, [*args, "--no-progress"], prog_name="phalanx")
    assert result.exit_code == 0, result.output
    svgs = sorted(p.name for p in tmp_path.glob("*.svg"))
    assert svgs == sorted(figures.figure_name(n, "svg") for n in figures.FIGURES)
    assert not list(tmp_path.glob("fig*.png"))


@pytest.mark.parametrize(
    ("option", "words"),
    [(["--format", "jpg"], ["--format", "png, pdf, svg"]), (["--dpi", "10"], ["--dpi"])],
)
def test_run_refuses_a_bad_format_or_dpi_naming_the_option(
    option: list[str], words: list[str], tmp_path: Path
) -> None:
    scenario = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
    args = ["run", str(scenario), "-o", str(tmp_path), *option]
    result = CliRunner().invoke(app, args, prog_name="phalanx")
    assert result.exit_code == 2
    for word in words:
        assert word in result.output
    assert not list(tmp_path.iterdir())


def test_save_figure_refuses_an_absurd_dpi(tmp_path: Path) -> None:
    fig = plt.figure()
    with pytest.raises(ValueError, match="dpi"):
        figures.save_figure(fig, tmp_path / "x.png", dpi=100_000)


def test_figure_4b_has_a_row_for_every_behaviour_state() -> None:
    assert sorted(STATE_ROWS) == sorted(State)  # a new state gets its place, not the top
    assert len(set(STATE_ROWS)) == len(STATE_ROWS)
