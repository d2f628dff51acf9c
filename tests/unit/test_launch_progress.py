"""`phalanx launch` talks as `phalanx up` does: the world's ticks (its row of the status
table) become the progress line of `phalanx.cli.progress.Reporter`, in seconds of run,
sparse in a pipe; on a terminal showing the live table, the line sits in its title."""

from __future__ import annotations

import io

from phalanx.cli.commands.deploy import TitleLine, WorldProgress
from phalanx.cli.progress import Reporter
from phalanx.hosts.fleet_output import LiveOutput, PlainOutput, Row


class Clock:
    """A clock the test moves."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _rows(world: str, process: str = "running") -> list[Row]:
    return [
        Row("r1", "robot-a", "running", 0, "NAVIGATE", "r1", 10.0, ""),
        Row("world", "laptop", process, 0, world, "-", None, ""),
    ]


def test_the_worlds_ticks_are_reported_in_seconds_of_run() -> None:
    stream, clock, printed = io.StringIO(), Clock(), []
    reporter = Reporter("launch", unit="s of run", stream=stream, tty=False, clock=clock)
    watched = WorldProgress(PlainOutput(printed.append, logs=False), reporter, rate_hz=10.0)
    watched.update(_rows("-"))  # before the world ticks: nothing to say
    assert stream.getvalue() == ""
    for tick in range(0, 2001, 20):  # 200 s of run, a row every 2 s of run
        clock.now = 5.0 + tick / 10.0  # (5 s to start, then real time)
        watched.update(_rows(f"tick {tick}/2000"))
    watched.update(_rows("-", process="finished"))
    lines = stream.getvalue().splitlines()
    assert lines[0] == "launch: 0 of 200 s of run (0 %), 5 s elapsed"
    assert "launch: 20 of 200 s of run (10 %), 25 s elapsed, about 4 min left" in lines
    assert lines[-1] == "launch: 200 of 200 s of run (100 %), 3 min elapsed, done"
    assert 10 <= len(lines) <= 13  # a pipe: every tenth of the run
    assert any("world on laptop" in line for line in printed)  # the output passed on


def test_on_a_terminal_the_live_tables_title_carries_the_line() -> None:
    clock = Clock()
    with LiveOutput("loopback · run x", logs=False) as live:
        line = TitleLine(live, "loopback · run x")
        reporter = Reporter("launch", unit="s of run", stream=line, tty=True, clock=clock)
        watched = WorldProgress(live, reporter, rate_hz=10.0)
        clock.now = 30.0
        watched.update(_rows("tick 600/2000"))
        assert live.title == (
            "loopback · run x · launch: 60 of 200 s of run (30 %), 30 s elapsed, about 1 min left"
        )
        reporter.close()  # (the end of the line: nothing to show)
        assert live.title.endswith("about 1 min left")


def test_quiet_says_nothing() -> None:
    stream = io.StringIO()
    reporter = Reporter("launch", unit="s of run", stream=stream, tty=False, quiet=True)
    WorldProgress(PlainOutput(lambda _: None), reporter, rate_hz=10.0).update(_rows("tick 10/100"))
    assert stream.getvalue() == ""
