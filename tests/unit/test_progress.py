"""Long commands talk: the progress line with the time left, sparse in a pipe, in place
in a terminal; a sweep's statement of its runs and time before it starts; `up --format`.
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from phalanx.analysis import sweep as sw
from phalanx.analysis.sweep_row import SweepRow
from phalanx.cli.commands.sweep import PER_RUN_S, statement
from phalanx.cli.commands.up import checkpoint_s
from phalanx.cli.progress import Reporter, duration, progress_line, sweep_statement
from phalanx.core.config_files import CONFIG_ROOT

WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"


class Clock:
    """A clock the test moves."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_the_line_counts_and_estimates_the_time_left_from_the_mean_so_far() -> None:
    line = progress_line("sweep", 30, 300, 600.0, unit="runs")
    # 30 runs in 10 min: 270 more at that rate are 90 min.
    assert line == "sweep: 30 of 300 runs (10 %), 10 min elapsed, about 1 h 30 min left"
    assert progress_line("report", 0, 21, 5.0).endswith("5 s elapsed")  # (no rate yet)
    assert progress_line("report", 21, 21, 117.0) == "report: 21 of 21 (100 %), 2 min elapsed, done"
    assert duration(float("nan")) == "?"


def test_a_pipe_gets_about_a_dozen_lines_for_a_thousand_updates() -> None:
    stream, clock = io.StringIO(), Clock()
    reporter = Reporter("report", unit="runs", stream=stream, tty=False, clock=clock)
    for done in range(1001):
        clock.now = done * 0.05  # 50 s in all: the 30 s period adds a line at most
        reporter(done, 1000)
    reporter.close()
    lines = stream.getvalue().splitlines()
    assert 10 <= len(lines) <= 13, lines
    assert "\r" not in stream.getvalue()
    assert lines[0].startswith("report: 0 of 1000 runs")
    assert lines[-1].endswith("done")


def test_a_terminal_gets_one_line_rewritten_in_place() -> None:
    stream, clock = io.StringIO(), Clock()
    reporter = Reporter("up", stream=stream, tty=True, clock=clock)
    for done in range(101):
        clock.now = float(done)
        reporter(done, 100)
    reporter.close()
    text = stream.getvalue()
    assert text.count("\r") == 101
    assert text.count("\n") == 1
    assert text.endswith("\n")
    assert text.rstrip().endswith("done")


def test_a_run_estimates_the_time_left_from_its_first_report_not_its_start_up() -> None:
    """`phalanx up` on robots takes a minute to start its processes; its run then goes at
    a second a second: counted in the rate, the start-up makes the run seem slow."""
    lines = {}
    for from_first in (False, True):
        stream, clock = io.StringIO(), Clock()
        reporter = Reporter("up", unit="s of run", stream=stream, tty=False, clock=clock,
                            from_first=from_first)  # fmt: skip
        for now, done in ((60.0, 3.0), (90.0, 33.0)):
            clock.now = now
            reporter(done, 240.0)
        lines[from_first] = stream.getvalue().splitlines()
    assert lines[True][0] == "up: 3 of 240 s of run (1 %), 1 min elapsed"  # (no rate yet)
    assert lines[True][1].endswith("2 min elapsed, about 3 min left")  # 207 s at 1 s/s
    assert lines[False][1].endswith("2 min elapsed, about 9 min left")  # 33 s of run in 90 s


def test_quiet_says_nothing() -> None:
    stream = io.StringIO()
    reporter = Reporter("sweep", stream=stream, tty=False, quiet=True)
    reporter.say("300 runs")
    reporter(1, 2)
    assert stream.getvalue() == ""


def test_a_sweep_states_its_runs_and_time_before_it_starts(tmp_path: Path) -> None:
    assert sweep_statement(300, 38.0, 2) == "300 runs, about 1 h 35 min on 2 workers"
    # The smallest sweep the CLI allows: one family, shape, size, controller and seed.
    todo = sw.jobs(["field"], ["wedge"], [3], range(1), ["ours"], [])
    out = tmp_path / "runs.jsonl"
    assert statement(todo, out, workers=2, address=None) == (
        f"1 run, about {duration(PER_RUN_S)} on 2 workers"
    )
    # Resumed: the runs done are not counted, and their mean wall time is the estimate.
    todo = sw.jobs(["field"], ["wedge"], [3], range(3), ["ours"], [])
    out.write_text(_record(todo[0], wall_s=20.0) + "\n", encoding="utf-8")
    assert statement(todo, out, workers=1, address=None) == (
        f"2 runs, about 40 s on 1 worker (1 of 3 in {out} already)"
    )
    # A line that holds no run's record is left out, and said so.
    with out.open("a", encoding="utf-8") as lines:
        lines.write(json.dumps({"key": todo[1].key, "wall_s": 20.0}) + "\n")
    assert statement(todo, out, workers=1, address=None) == (
        f"2 runs, about 40 s on 1 worker (1 of 3 in {out} already); 1 line of {out} holds "
        "no run's record, left out"
    )


def _record(job: sw.Job, *, wall_s: float) -> str:
    """A results line of `job` that took `wall_s` (its metrics made up, in range)."""
    stat = {"mean": 0.5, "max": 1.0}
    calm = {"samples": 10, **dict.fromkeys(sw.CALM_KEYS, stat)}
    row = SweepRow.model_validate({
        "job": dataclasses.asdict(job), "key": job.key, "wall_s": wall_s, "route_s": 100.0,
        "goal_reached": True, "time_to_goal_s": 120.0, "collisions_obstacle": 0,
        "collisions_robot": 0, "deadlock_reverses": 0, "leadership_changes": 0,
        "stuck": False, "stuck_reason": "", "episode_share": 0.1, "calm": calm,
    })  # fmt: skip
    return row.model_dump_json()


def test_a_checkpoint_gives_the_run_time_reached_and_a_stale_or_torn_one_nothing(
    tmp_path: Path,
) -> None:
    path = tmp_path / "metrics.json"
    assert checkpoint_s(path, 0.1, since_unix=0.0) is None
    reason = {"incomplete_reason": "a checkpoint of a run still going: 420 ticks run"}
    path.write_text(json.dumps(reason), encoding="utf-8")
    assert checkpoint_s(path, 0.1, since_unix=0.0) == 42.0
    assert checkpoint_s(path, 0.1, since_unix=path.stat().st_mtime + 10) is None
    reason["incomplete_reason"] = "a checkpoint: the world ran 977 of 2000 ticks; no report"
    path.write_text(json.dumps(reason), encoding="utf-8")
    assert checkpoint_s(path, 0.1, since_unix=0.0) == pytest.approx(97.7)
    path.write_text('{"incomplete_reason": "a checkpoint', encoding="utf-8")
    assert checkpoint_s(path, 0.1, since_unix=0.0) is None


@pytest.mark.timeout(240)  # its child processes' own bound, and set-up
def test_up_writes_svg_figures_when_asked(tmp_path: Path) -> None:
    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, "-m", "phalanx", "up", str(WEDGE), "--fleet", f"progress-{os.getpid()}",
         "--set", "duration_s=10", "--timeout", "120", "--no-recording", "--out", str(out),
         "--format", "svg", "--dpi", "100"],
        capture_output=True, text=True, timeout=180, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    svgs = sorted(p.name for p in out.glob("fig*.svg"))
    assert svgs, sorted(p.name for p in out.iterdir())
    assert not list(out.glob("fig*.png"))


def test_the_report_matrix_reports_each_run_as_it_finishes(tmp_path: Path) -> None:
    from phalanx.analysis.report import Case, run_matrix

    calls: list[tuple[int, int]] = []
    results = run_matrix(
        [Case("wedge", "ours")], tmp_path, workers=1, progress=lambda d, t: calls.append((d, t))
    )
    assert calls == [(0, 1), (1, 1)]
    assert results[0]["controller"] == "ours"
