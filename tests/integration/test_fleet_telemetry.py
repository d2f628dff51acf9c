"""Telemetry across processes: `phalanx up` with recording on writes one recording (one
id, every process's part merged) that reads back with every robot's entities, the
`sim_time` timeline, and one logged control step per executed step."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from phalanx.core.config_files import CONFIG_ROOT
from phalanx.telemetry.rrd import summarize
from phalanx.wire.transport import free_tcp_port

pytestmark = pytest.mark.integration
WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
PER_ROBOT = ("pose", "heading", "trail", "cmd/v_mps", "cmd/omega_degps", "measured/v_mps",
             "measured/omega_degps", "fsm", "state")  # fmt: skip
PER_FOLLOWER = ("slot_target", "errors/linear_pct", "errors/angular_pct", "errors/orientation_deg")


@pytest.mark.timeout(360)  # its child processes' own bound, and set-up
def test_up_recording_reads_back_whole(tmp_path: Path) -> None:
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "phalanx", "up", str(WEDGE), "--out", str(out),
         "--fleet", "rec", "--timeout", "240", "--set", "duration_s=60"],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    parts = sorted(p.name for p in (out / "telemetry").glob("*.rrd"))
    assert parts == ["r1.rrd", "r2.rrd", "r3.rrd", "world.rrd"]
    summary = summarize(out / "run.rrd")
    assert len(summary.recording_ids) == 1  # one recording shared by every process
    assert "sim_time" in summary.timelines
    steps = {rid: r["steps"] for rid, r in json.loads((out / "metrics.json").read_text())[
        "runtime"]["agents"].items()}  # fmt: skip
    assert steps == {"r1": 600, "r2": 600, "r3": 600}
    rows = summary.rows
    for rid, executed in steps.items():
        assert rows[f"/robots/{rid}/pose"] == executed, rid  # every step logged, none twice
        assert rows[f"/world/truth/{rid}"] == executed
        for name in PER_ROBOT:
            assert rows[f"/robots/{rid}/{name}"] > 0, (rid, name)
    for rid in ("r2", "r3"):
        for name in PER_FOLLOWER:
            assert rows[f"/robots/{rid}/{name}"] >= steps[rid] - 1, (rid, name)
    assert rows["/bounds/errors/linear_pct"] > 0
    assert rows["/bounds/velocity/v_max_mps"] > 0


@pytest.mark.timeout(360)  # its child processes' own bound, and set-up
def test_a_dead_viewer_costs_the_fleet_nothing_but_counted_drops(tmp_path: Path) -> None:
    out = tmp_path / "run"
    dead = f"rerun+http://127.0.0.1:{free_tcp_port()}/proxy"  # nothing listens there
    proc = subprocess.run(
        [sys.executable, "-m", "phalanx", "up", str(WEDGE), "--out", str(out), "--fleet", "dead",
         "--timeout", "240", "--set", "duration_s=20", "--telemetry-url", dead],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    agents = json.loads((out / "metrics.json").read_text())["runtime"]["agents"]
    assert {rid: a["steps"] for rid, a in agents.items()} == {"r1": 200, "r2": 200, "r3": 200}
    for rid, report in agents.items():  # every step's entry missed the viewer, and says so
        assert report["telemetry_dropped"] >= report["steps"], rid
    rows = summarize(out / "run.rrd").rows  # ... while the recording kept everything
    assert all(rows[f"/robots/{rid}/pose"] == 200 for rid in agents)
