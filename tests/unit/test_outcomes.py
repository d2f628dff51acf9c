"""How a run of processes says how it ended: results marked whole or not, the deaths a
launch reports, what `phalanx status` shows of each process's drops, exit codes in words."""

from __future__ import annotations

import json
from pathlib import Path

from phalanx.analysis.results import mark_results
from phalanx.hosts.deployment import load_deployment
from phalanx.hosts.fleet_client import FleetWatch
from phalanx.hosts.fleet_output import fleet_rows, render_table, rows_as_json
from phalanx.hosts.launch import deaths
from phalanx.hosts.protocol import ChildStatus, HostStatus
from phalanx.runtime.exits import EXIT_RUN_CUT_SHORT, agent_exit_reason, exit_reason


def test_results_are_marked_complete_or_not_with_every_reason(tmp_path: Path) -> None:
    whole = tmp_path / "whole"
    whole.mkdir()
    (whole / "metrics.json").write_text(json.dumps({"runtime": {"incomplete_reason": ""}}))
    assert mark_results(whole, problems=[])["complete"] is True
    cut = tmp_path / "cut"
    cut.mkdir()
    runtime = {"incomplete_reason": "robot r3 went away at tick 80"}
    (cut / "metrics.json").write_text(json.dumps({"followers": {}, "runtime": runtime}))
    marked = mark_results(cut, problems=["agent r3: killed by SIGKILL after 8.1 s"])
    assert marked["complete"] is False
    assert marked["incomplete_reason"] == (
        "agent r3: killed by SIGKILL after 8.1 s; robot r3 went away at tick 80"
    )
    assert json.loads((cut / "metrics.json").read_text())["followers"] == {}  # kept
    nothing = tmp_path / "world-died"  # no metrics at all: the mark alone
    marked = mark_results(nothing, problems=["world: killed by SIGKILL after 3.0 s"])
    assert marked["complete"] is False
    assert "the world wrote no metrics" in marked["incomplete_reason"]


def _host(*children: ChildStatus) -> HostStatus:
    return HostStatus(host="robot-b", fleet="f", deployment="d", digest="0" * 64,
                      time_unix=0.0, uptime_s=1.0, children=children)  # fmt: skip


def test_a_launch_names_every_process_that_died_on_its_own() -> None:
    statuses: dict[str, HostStatus | None] = {
        "robot-b": _host(
            ChildStatus(
                name="r2",
                kind="agent",
                state="running",
                restarts=1,
                crashes=1,
                last_error="killed by SIGKILL",
            ),
            ChildStatus(name="r3", kind="agent", state="stopped", exit_code=0),
            ChildStatus(
                name="world", kind="world", state="failed", crashes=1, last_error="exit 1: boom"
            ),
        ),
        "robot-a": None,
    }
    assert deaths(statuses) == [
        "r2 on robot-b: killed by SIGKILL, restarted 1x",
        "world on robot-b: exit 1: boom",
    ]


def test_status_shows_what_each_process_dropped_and_how_often_it_relinked() -> None:
    loaded = load_deployment("loopback")
    processes = {
        "r2": {"robot_id": "r2", "dropped": 9847, "relinks": 2},
        "r3": {"robot_id": "r3", "relinks": True},  # not a count: shown as unknown
        "world": {"tick": 5, "dropped": 3, "relinks": 0},
    }
    rows = fleet_rows(loaded, {}, FleetWatch(), world=processes["world"], processes=processes)
    dropped = {row.name: row.dropped for row in rows}
    assert dropped == {"r1": None, "r2": 9847, "r3": None, "world": 3}
    assert {row.name: row.relinks for row in rows} == {"r1": None, "r2": 2, "r3": None, "world": 0}
    columns = render_table(rows, title="t").columns
    assert [c.header for c in columns[7:9]] == ["dropped", "relinks"]
    assert rows_as_json(rows)[1]["relinks"] == 2  # `phalanx status --json`


def test_exit_codes_in_words() -> None:
    assert exit_reason(-9) == "killed by SIGKILL"
    assert exit_reason(4) == "exit 4"
    assert agent_exit_reason(EXIT_RUN_CUT_SHORT) == (
        "exit 4 (the world ended the run before its last tick)"
    )
