"""What live Rerun telemetry costs a control step, and how big recordings get.

Runs the paper scenario with `phalanx up` (lockstep, one process per robot) with the
recording off and on, alternately, and prints each agent's control-step time (the agent
core's step, publishing, and the telemetry calls; measured inside the agent process,
p50/p99), the run's real-time factor, entries the telemetry dropped, and the size of the
merged recording per robot-minute of simulated time.

    .venv/bin/python bench/bench_telemetry.py [--repeats 2]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from calibration import Calibration

from phalanx.core.config_files import CONFIG_ROOT, load_scenario

WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"


def up(out: Path, *, recording: bool) -> dict[str, object]:
    """One `phalanx up` run; its metrics.json."""
    argv = [sys.executable, "-m", "phalanx", "up", str(WEDGE), "--out", str(out)]
    argv += [] if recording else ["--no-recording"]
    subprocess.run(argv, check=True, capture_output=True, timeout=900)
    metrics: dict[str, object] = json.loads((out / "metrics.json").read_text())
    return metrics


def main() -> None:
    Calibration.measure()  # (the unit every time below can be divided by, on any machine)
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    scenario = load_scenario(WEDGE)
    robot_minutes = len(scenario.robots) * scenario.duration_s / 60.0
    print("recording  run  step_p50_us  step_p99_us  realtime_x  dropped  rrd_MB  MB_per_robot_min")
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeats):
            for recording in (False, True):
                out = Path(tmp) / f"{recording}-{i}"
                metrics = up(out, recording=recording)
                runtime = metrics["runtime"]
                assert isinstance(runtime, dict)  # noqa: S101
                agents = runtime["agents"].values()
                p50 = statistics.median(a["step_p50_us"] for a in agents)
                p99 = max(a["step_p99_us"] for a in agents)
                dropped = sum(a["telemetry_dropped"] for a in agents)
                size = (out / "run.rrd").stat().st_size / 1e6 if recording else 0.0
                print(
                    f"{'on' if recording else 'off':9s}  {i:3d}  {p50:11.0f}  {p99:11.0f}  "
                    f"{metrics['realtime_factor']:10.1f}  {dropped:7d}  {size:6.2f}  "
                    f"{size / robot_minutes:16.3f}",
                    flush=True,
                )


if __name__ == "__main__":
    main()
