"""What the ROS 2 bridge costs a fleet: a real-time fleet of `--robots` robots at 10 Hz
(the world and one agent per robot, each its own process, on a loopback router), the
bridge (`phalanx ros2`) joined to it, and the CPU time each process used over a window
after start-up, read from /proc. Prints the agents' mean, the bridge's, and the bridge's
share of one agent and of all of them, beside the calibration workload timed in the same
run (docs/ROS2.md).

    .venv/bin/python bench/bench_ros2_bridge.py                 # 10 robots, 20 s window
    .venv/bin/python bench/bench_ros2_bridge.py --robots 3 --window 10
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "lab"))

from calibration import Calibration
from fleetlab import terminate

from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.core.scenarios import grid_scenario
from phalanx.wire.transport import free_tcp_port, loopback_endpoint

CLI = [sys.executable, "-m", "phalanx"]
START_UP_S = 12.0  # every process joined and stepping before the window opens


def cpu_s(pid: int) -> float:
    """User + system CPU time (s) process `pid` has used."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def start(folder: Path, robots: int) -> dict[str, subprocess.Popen[bytes]]:
    """The world, the agents and the bridge, on one loopback router (the world's)."""
    base = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
    scenario = grid_scenario(base, robots, duration_s=START_UP_S + 600.0)
    path = folder / "grid.json"
    path.write_text(scenario.model_dump_json())
    endpoint = loopback_endpoint(free_tcp_port())
    common = ["--fleet", "bench", "--clock", "realtime"]
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    world = [*CLI, "world", str(path), *common, "--listen", endpoint, "--no-recording"]
    procs = {"world": subprocess.Popen([*world, "--out", str(folder / "out")], **quiet)}
    time.sleep(2.0)
    for entry in scenario.robots:
        agent = [*CLI, "agent", str(path), "--robot", entry.id, *common, "--mode", "client"]
        procs[entry.id] = subprocess.Popen([*agent, "--connect", endpoint], **quiet)
    bridge = [*CLI, "ros2", str(path), "--fleet", "bench", "--mode", "client"]
    procs["bridge"] = subprocess.Popen([*bridge, "--connect", endpoint], **quiet)
    return procs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=10)
    parser.add_argument("--window", type=float, default=20.0, help="seconds measured")
    args = parser.parse_args()
    cal = Calibration.measure()
    with tempfile.TemporaryDirectory() as tmp:
        procs = start(Path(tmp), args.robots)
        try:
            time.sleep(START_UP_S)
            dead = [name for name, p in procs.items() if p.poll() is not None]
            if dead:
                sys.exit(f"not running after start-up: {', '.join(dead)}")
            before = {name: cpu_s(p.pid) for name, p in procs.items()}
            time.sleep(args.window)
            after = {name: cpu_s(p.pid) for name, p in procs.items()}
        finally:
            terminate(procs.values(), grace_s=10.0)
    share = {name: (after[name] - before[name]) / args.window for name in procs}
    agents = [share[name] for name in procs if name not in ("world", "bridge")]
    mean = sum(agents) / len(agents)
    bridge = share["bridge"]
    print(f"{args.robots} robots at 10 Hz, {args.window:.0f} s measured")
    print(f"world   {100 * share['world']:.2f} % of a core")
    print(f"agents  {100 * mean:.2f} % of a core each ({cal.cal(mean)} per second)")
    print(f"bridge  {100 * bridge:.2f} % of a core ({cal.cal(bridge)} per second)")
    whole = 100 * bridge / sum(agents)
    print(f"bridge / one agent {100 * bridge / mean:.0f} %, / all agents {whole:.1f} %")


if __name__ == "__main__":
    main()
