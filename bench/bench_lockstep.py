"""Lockstep speed of the paper scenario in separate processes (`phalanx up`).

Runs the 200 s paper wedge (3 robots, 10 Hz) as one world process and three agent
processes over Zenoh on loopback, with and without the Rerun recording, and prints the
simulated-time wall clock (what the world measures from the first to the last tick),
the real-time factor, the whole command's wall time (process start-up and results
included), and the world's frame -> answer round trip (the robot's state, which
carries its command). The in-process batch run of the same scenario is printed beside
it for the ratio. `phalanx up` pins each process to one CPU in lockstep; every run is
repeated with `--no-pin`, pinned and unpinned alternating, for the ratio between them.

    .venv/bin/python bench/bench_lockstep.py [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from calibration import Calibration, load

from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.runtime.batch import run_batch

WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"


def up(out: Path, *, recording: bool, pin: bool) -> tuple[float, dict[str, object]]:
    """Run `phalanx up` once; return (command wall time, metrics.json)."""
    argv = [sys.executable, "-m", "phalanx", "up", str(WEDGE), "--out", str(out)]
    if not recording:
        argv.append("--no-recording")
    if not pin:
        argv.append("--no-pin")
    started = time.monotonic()
    subprocess.run(argv, check=True, capture_output=True, timeout=600)
    return time.monotonic() - started, json.loads((out / "metrics.json").read_text())


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    cal = Calibration.measure()
    scenario = load_scenario(WEDGE)
    started = time.perf_counter()
    run_batch(scenario)
    batch_s = time.perf_counter() - started
    print(
        f"paper wedge, {scenario.duration_s:.0f} s at {scenario.control_rate_hz:.0f} Hz; "
        f"in process: {batch_s:.2f} s ({cal.cal(batch_s)}, "
        f"{scenario.duration_s / batch_s:.0f}x real time)"
    )
    print(
        "recording  pin  run  sim_wall_s  sim_wall_cal  realtime_x  command_wall_s  "
        "resp_p50_ms  resp_p99_ms  load"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for recording in (False, True):
            for i in range(args.repeats):
                for pin in (True, False):
                    where = Path(tmp) / f"{recording}-{pin}-{i}"
                    wall, metrics = up(where, recording=recording, pin=pin)
                    row(recording, pin, i, wall, metrics, cal)
    Calibration.measure()


def row(
    recording: bool, pin: bool, i: int, wall: float, metrics: dict[str, object], cal: Calibration
) -> None:
    """One run's line of the table."""
    rt = metrics["runtime"]
    assert isinstance(rt, dict)  # noqa: S101
    print(
        f"{'on' if recording else 'off':9s}  {'yes' if pin else 'no':3s}  {i:3d}  "
        f"{metrics['wall_time_s']:10.2f}  {cal.ratio(metrics['wall_time_s']):12.0f}  "
        f"{metrics['realtime_factor']:10.1f}  "
        f"{wall:14.2f}  {1e3 * rt['response_p50_s']:11.2f}  "
        f"{1e3 * rt['response_p99_s']:11.2f}  {load()}",
        flush=True,
    )


if __name__ == "__main__":
    main()
