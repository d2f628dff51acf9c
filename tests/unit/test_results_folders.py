"""One naming rule for results folders, and no silent overwrite: `results/<scenario>-
<controller>` (`-up`, `-world` after it for those commands), a numbered suffix for a
folder that holds an earlier run, `--force` to write into it; `report` into a results
folder unless asked for docs/ (the same bytes either way); every command naming the
folder it wrote."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from phalanx.analysis.report import Case, write_report
from phalanx.cli import app
from phalanx.cli.outputs import fresh_folder, launch_run_id, results_name
from phalanx.core.config_files import CONFIG_ROOT
from phalanx.hosts.protocol import RUN_ID_PATTERN

REPO = Path(__file__).resolve().parents[2]
WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
QUICK = ["--set", "duration_s=2", "--no-figures", "--no-recording", "--no-progress"]


def test_the_rule_names_the_scenario_the_controller_and_the_command() -> None:
    assert results_name("paper-wedge", "ours") == Path("results/paper-wedge-ours")
    assert results_name("paper-wedge", "icr", "up") == Path("results/paper-wedge-icr-up")
    assert results_name("nav-field", "ours", "world") == Path("results/nav-field-ours-world")


def test_a_folder_that_holds_anything_gets_the_next_free_suffix(tmp_path: Path) -> None:
    named = tmp_path / "results" / "x-ours"
    assert fresh_folder(named) == named  # new: taken, and made
    assert named.is_dir()
    assert fresh_folder(named) == named  # still empty: used
    (named / "metrics.json").write_text("{}")
    assert fresh_folder(named) == tmp_path / "results" / "x-ours-2"
    assert fresh_folder(named) == tmp_path / "results" / "x-ours-2"  # (made, still empty)
    (tmp_path / "results" / "x-ours-2" / "run.rrd").write_text("")
    assert fresh_folder(named) == tmp_path / "results" / "x-ours-3"
    assert fresh_folder(named, force=True) == named
    assert (named / "metrics.json").read_text() == "{}"  # nothing removed
    file = tmp_path / "a-file"
    file.write_text("not a folder")
    assert fresh_folder(file) == tmp_path / "a-file-2"


def _run(*args: str) -> str:
    result = CliRunner().invoke(app, ["run", str(WEDGE), *QUICK, *args], prog_name="phalanx")
    assert result.exit_code == 0, result.output
    return result.output


def test_run_writes_a_second_run_beside_the_first_and_says_where(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    first = tmp_path / "results" / "paper-wedge-ours"
    assert _run().splitlines()[-1] == "results: results/paper-wedge-ours"
    before = (first / "metrics.json").read_bytes()
    assert _run().splitlines()[-1] == "results: results/paper-wedge-ours-2"
    assert (first / "metrics.json").read_bytes() == before  # the first run untouched
    assert (tmp_path / "results" / "paper-wedge-ours-2" / "metrics.json").is_file()
    assert _run("--controller", "icr").splitlines()[-1] == "results: results/paper-wedge-icr"
    assert _run("--force").splitlines()[-1] == "results: results/paper-wedge-ours"
    assert not (tmp_path / "results" / "paper-wedge-ours-3").exists()
    assert (first / "metrics.json").read_bytes() != before  # (its wall time differs)


def test_run_gives_a_taken_out_folder_a_suffix_too(tmp_path: Path) -> None:
    out = tmp_path / "mine"
    _run("--out", str(out))
    said = _run("--out", str(out)).splitlines()[-1]
    assert said == f"results: {tmp_path / 'mine-2'}"


def test_a_launch_run_is_named_after_its_deployment_and_time() -> None:
    one, two = launch_run_id("loopback"), launch_run_id("loopback")
    for run_id in (one, two):
        assert re.fullmatch(RUN_ID_PATTERN, run_id)
        assert re.fullmatch(r"loopback-\d{8}-\d{6}-[0-9a-f]{4}", run_id)
    assert one != two  # two launches in one second are two runs
    long = launch_run_id("a-deployment-with-a-very-long-name-indeed-" + "x" * 20)
    assert re.fullmatch(RUN_ID_PATTERN, long)
    assert len(long) <= 40


def test_report_writes_the_same_bytes_into_a_results_folder_as_into_docs(
    tmp_path: Path,
) -> None:
    """One case of the matrix (the wedge with ours), written into a results folder and
    into a copy of docs/: the same RESULTS.md, the same figures, the sections the
    benchmarks wrote kept from docs/RESULTS.md; and the wedge's paper.pdf."""
    docs = tmp_path / "docs"
    docs.mkdir()
    shutil.copyfile(REPO / "docs" / "RESULTS.md", docs / "RESULTS.md")
    cases = [Case("wedge", "ours")]
    out = tmp_path / "results" / "report"
    write_report(out, out, workers=1, cases=cases, kept_from=docs / "RESULTS.md")
    write_report(docs, tmp_path / "runs", workers=1, cases=cases)
    assert (out / "RESULTS.md").read_bytes() == (docs / "RESULTS.md").read_bytes()
    figures = sorted(p.name for p in (out / "figures").iterdir())
    assert figures == sorted(p.name for p in (docs / "figures").iterdir())
    assert len(figures) == 3  # the wedge's figures 5, 6 and 7
    for name in figures:
        assert (out / "figures" / name).read_bytes() == (docs / "figures" / name).read_bytes()
    text = (out / "RESULTS.md").read_text(encoding="utf-8")
    assert "<!-- sweep: written by phalanx sweep -->" in text  # kept from docs/
    assert (out / "wedge-ours" / "paper.pdf").read_bytes().startswith(b"%PDF-")


def test_report_takes_a_results_folder_of_its_own_unless_forced(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The folder `phalanx report` picks (its runs are 2 minutes: the choice alone)."""
    monkeypatch.chdir(tmp_path)
    from phalanx.cli.commands.report import REPORT_FOLDER

    taken = fresh_folder(REPORT_FOLDER)
    (taken / "RESULTS.md").write_text("an earlier report")
    assert fresh_folder(REPORT_FOLDER) == Path("results/report-2")
    assert fresh_folder(REPORT_FOLDER, force=True) == Path("results/report")
