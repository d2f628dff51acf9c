"""The paper scenario with every robot on the `arcos` driver: `phalanx up --driver arcos`
runs one ARCOS emulator per robot (moved by the world process) and agents that only see
ARCOS over TCP. The formation must come out as it does with the `sim` driver."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from phalanx.analysis.metrics import run_metrics
from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_scenario
from phalanx.core.scenarios import signal_builder
from phalanx.runtime.batch import run_batch

pytestmark = [pytest.mark.integration, pytest.mark.drivers]
WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
# 45 s of real time: the deadlock at 20 s, a 1.5 m reverse, forwards again.
# (the paper's signal builder at 20 s: the scenario's wall is reached at about 97 s)
# Handover off, as the paper has none: in lockstep every robot is blocked at the same
# step, while ARCOS's sonar ring reports the block a sonar at a time, so a follower may
# still see its path clear when the leader has been blocked for `confirm_s`, and take
# the lead (or the fleet hand it over); the runs would then differ by who leads. What
# follows such a race is tested on its own (tests/unit/test_leadership.py,
# tests/property/test_leadership_properties.py).
SHORT = [
    "duration_s=45", *signal_builder(20.0), "deadlock.safe_distance_m=1.5",
    "leadership.handover=false",
]  # fmt: skip
# ARCOS quantises what the agents see and send (1 mm, 0.088 deg and 1 mm/s in SIPs; VEL in
# mm/s, RVEL in whole deg/s) and runs on the wall clock of a shared machine; a SIP is up to
# 100 ms old when a step reads it, which the agent dead-reckons away (and the emulator
# reports the body where it is when the SIP goes, not at the world's last tick). Measured
# over 3 runs: backward RMS within 0.05 of the sim driver's lockstep run; without either
# correction a follower keeps a steady lag set by the SIP phase, up to 0.8 % linear.
TOLERANCE = {"linear_pct": 0.2, "angular_pct": 0.1, "orientation_deg": 0.3}
BOUNDS = {"linear_pct": 2.0, "angular_pct": 0.8, "orientation_deg": 1.3}


@pytest.mark.timeout(260)  # its child processes' own bound, and set-up
def test_up_on_arcos_emulators_keeps_the_formation(tmp_path: Path) -> None:
    out = tmp_path / "arcos"
    sets = [arg for s in SHORT for arg in ("--set", s)]
    proc = subprocess.run(
        [sys.executable, "-m", "phalanx", "up", str(WEDGE), "--driver", "arcos",
         "--out", str(out), "--no-recording", "--timeout", "150", *sets],
        capture_output=True, text=True, timeout=200, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    arcos = json.loads((out / "metrics.json").read_text())
    sim = run_metrics(run_batch(apply_overrides(load_scenario(WEDGE), SHORT)))
    assert arcos["deadlock_reverses"] == sim["deadlock_reverses"] == 1, arcos["transitions"]
    assert arcos["collisions"] == []
    for rid in ("r2", "r3"):
        got, want = arcos["followers"][rid]["backward"], sim["followers"][rid]["backward"]
        for key, bound in BOUNDS.items():
            assert got[key]["max"] < bound, (rid, key, got[key], want[key])
            assert abs(got[key]["rms"] - want[key]["rms"]) < TOLERANCE[key], (
                rid, key, got[key], want[key],
            )  # fmt: skip
    reports = arcos["runtime"]["agents"]
    assert sorted(reports) == ["r1", "r2", "r3"]
    assert all(r["steps"] >= 400 for r in reports.values())
    assert all(r["dropped_messages"] == 0 for r in reports.values())
