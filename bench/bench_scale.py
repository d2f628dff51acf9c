"""How many agent processes this machine holds at 10 Hz, and what each one costs.

For each fleet size, a grid formation behind the paper's leader script is written to a
scenario file and run by `phalanx up --clock realtime` (one world process, one process
per robot, Zenoh on loopback). While it runs, every child's CPU time and resident memory
are sampled from /proc. The world measures, for every command, the time from the tick's
sense frames being published to the command arriving; the deadline is the 100 ms
control period.

    .venv/bin/python bench/bench_scale.py [--robots 10 20 30 40] [--seconds 30]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from calibration import Calibration

from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_scenario
from phalanx.core.scenarios import grid_scenario

CLK_TCK = os.sysconf("SC_CLK_TCK")
PAGE_B = os.sysconf("SC_PAGE_SIZE")


@dataclass
class Usage:
    """CPU seconds and peak resident memory of one process."""

    cpu_s: float = 0.0
    rss_peak_b: int = 0
    argv: list[str] = field(default_factory=list)


def _children(pid: int) -> list[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return []
    return [int(p) for p in text.split()]


def _sample(pid: int, usage: dict[int, Usage]) -> None:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        statm = Path(f"/proc/{pid}/statm").read_text().split()
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")
    except (OSError, IndexError):
        return
    u = usage.setdefault(pid, Usage(argv=argv))
    u.cpu_s = (int(stat[11]) + int(stat[12])) / CLK_TCK  # utime + stime
    u.rss_peak_b = max(u.rss_peak_b, int(statm[1]) * PAGE_B)


def run(n: int, seconds: float, workdir: Path) -> dict[str, object]:
    """Run an `n`-robot fleet in real time; return the figures."""
    base = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
    scenario = apply_overrides(grid_scenario(base, n, duration_s=seconds), [])
    path = workdir / f"grid{n}.json"
    path.write_text(scenario.model_dump_json(), encoding="utf-8")
    out = workdir / f"grid{n}"
    argv = [
        sys.executable,
        "-m",
        "phalanx",
        "up",
        str(path),
        "--clock",
        "realtime",
        "--no-recording",
        "--out",
        str(out),
        "--timeout",
        str(seconds + 300),
    ]
    usage: dict[int, Usage] = {}
    started = time.monotonic()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    while proc.poll() is None:
        for child in _children(proc.pid):
            _sample(child, usage)
        time.sleep(0.5)
    wall_s = time.monotonic() - started
    if proc.returncode != 0:
        err = proc.stderr.read().decode()[-2000:] if proc.stderr else ""
        raise RuntimeError(f"phalanx up of {n} robots failed ({proc.returncode}):\n{err}")
    runtime = json.loads((out / "metrics.json").read_text())["runtime"]
    agents = [u for u in usage.values() if "agent" in u.argv]
    world = [u for u in usage.values() if "world" in u.argv]
    return {
        "robots": n,
        "wall_s": wall_s,
        "runtime": runtime,
        "agent_cpu_pct": 100 * sum(a.cpu_s for a in agents) / max(len(agents), 1) / wall_s,
        "agent_rss_mib": max((a.rss_peak_b for a in agents), default=0) / 2**20,
        "world_cpu_pct": 100 * sum(w.cpu_s for w in world) / wall_s,
        "world_rss_mib": max((w.rss_peak_b for w in world), default=0) / 2**20,
    }


def main() -> None:
    Calibration.measure()  # (the unit every time below can be divided by, on any machine)
    parser = argparse.ArgumentParser()
    parser.add_argument("--robots", type=int, nargs="+", default=[10, 20, 30, 40])
    parser.add_argument("--seconds", type=float, default=30.0)
    args = parser.parse_args()
    print(f"real-time fleets at 10 Hz on {os.cpu_count()} cores, {args.seconds:.0f} s each")
    print(
        "robots  resp_p50_ms  resp_p99_ms  late  missed  overruns  deadline  "
        "agent_cpu_%  agent_rss_MiB  world_cpu_%"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.robots:
            r = run(n, args.seconds, Path(tmp))
            rt = r["runtime"]
            assert isinstance(rt, dict)  # noqa: S101
            missed = sum(rt["missed_deadlines"].values())
            met = (rt["response_p99_s"] or 1e9) < rt["period_s"] and rt["overruns"] == 0
            print(
                f"{n:6d}  {1e3 * rt['response_p50_s']:11.2f}  {1e3 * rt['response_p99_s']:11.2f}"
                f"  {rt['commands_late']:4d}  {missed:6d}  {rt['overruns']:8d}  "
                f"{'met' if met else 'MISSED':>8s}  {r['agent_cpu_pct']:11.1f}  "
                f"{r['agent_rss_mib']:13.1f}  {r['world_cpu_pct']:11.1f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
