"""`PHALANX_PROFILE=<folder>`: every phalanx process writes its cProfile there (how the
processes of a fleet are profiled)."""

from __future__ import annotations

import os
import pstats
import subprocess
import sys
from pathlib import Path


def test_a_command_writes_its_profile(tmp_path: Path) -> None:
    env = {**os.environ, "PHALANX_PROFILE": str(tmp_path)}
    done = subprocess.run(
        [sys.executable, "-m", "phalanx", "fsm", "--table"],
        env=env, cwd=tmp_path, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    (profile,) = tmp_path.glob("fsm-*.prof")
    functions = {name for _, _, name in pstats.Stats(str(profile)).stats}  # type: ignore[attr-defined]
    assert "fsm" in functions  # the command's own function ran under the profiler
