"""`phalanx fsm`: Mermaid on stdout, the diagram as a PNG, the arbitration table."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from phalanx.cli import app


def test_fsm_prints_mermaid_and_writes_the_diagram(tmp_path: Path) -> None:
    png = tmp_path / "fsm.png"
    result = CliRunner().invoke(app, ["fsm", "--png", str(png), "--table"])
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith("stateDiagram-v2")
    for state in ("NAVIGATE", "DEADLOCK_REVERSE", "FORMATION_REVERSE", "STUCK", "AVOID"):
        assert f"--> {state}" in result.stdout
    assert "| 100 | `STUCK` |" in result.stdout
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert png.stat().st_size > 20_000


@pytest.mark.timeout(180)  # its child processes' own bound, and set-up
def test_fsm_as_a_real_command(tmp_path: Path) -> None:
    png = tmp_path / "chart.png"
    proc = subprocess.run(
        [sys.executable, "-m", "phalanx", "fsm", "--png", str(png)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert "stateDiagram-v2" in proc.stdout
    assert png.exists()
