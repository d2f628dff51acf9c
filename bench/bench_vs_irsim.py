"""phalanx against IR-SIM (a peer users pick for multi-robot simulation in Python), side by
side: the same grid of N differential-drive robots at 10 Hz among the same circles.

IR-SIM 2.12 (the `bench` extra: `pip install -e '.[bench]'`): every robot a `diff`
kinematics disc with a 16-beam `lidar2d`, its `dash` behaviour (straight for a goal 40 m
ahead), collisions `stop`, no rendering. phalanx: the paper scenario's grid formation
(`grid_scenario`) with the same circles added: 16 sonars of 3 rays each (48 rays), the
whole agent stack per robot (leadership, sensing with the formation's own robots masked
out, behaviour state machine, controller, limiter), and the world's integration in 4
sub-steps with contacts. Each side runs in its own fresh process; the loop is timed
inside it, the whole process (interpreter start, imports, building, the loop) from
outside (phalanx's sources byte-compiled first, as an installed package's are). Each
cell is the median of `--repeats` runs; every time is also given in
units of the calibration workload timed in the same run (`bench/calibration.py`).

    .venv/bin/python bench/bench_vs_irsim.py [--robots 3 10 50 200 1000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import compileall
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from calibration import Calibration, load

STEPS = {3: 2000, 10: 1000, 50: 300, 200: 100, 1000: 30}
SPACING_M = 2.0
RADIUS_M = 0.25


def circles(n: int) -> list[tuple[float, float, float]]:
    """Obstacle circles beside and ahead of the grid (x, y, radius), the same for both."""
    cols = max(1, -(-n // max(1, int(n**0.5))))
    rows = -(-n // cols)
    xs = [-rows * SPACING_M + 4.0 * k for k in range(int((rows * SPACING_M + 40) / 4.0))]
    return [(x, 2.5, 0.3) for x in xs] + [(x, -cols * SPACING_M - 0.5, 0.3) for x in xs]


def phalanx_scenario(n: int, steps: int) -> Any:
    """The phalanx side's scenario for `n` robots and `steps` steps, as `PHALANX` builds
    it in its fresh process (which imports phalanx alone, so it spells it out itself).
    """
    from phalanx.core.config import Scenario
    from phalanx.core.config_files import CONFIG_ROOT, load_scenario, validate_data
    from phalanx.core.scenarios import grid_scenario

    base = grid_scenario(load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml"), n)
    data = base.model_dump()
    data["duration_s"] = steps / base.control_rate_hz
    data["world"]["circles"] = [{"x_m": x, "y_m": y, "radius_m": r} for x, y, r in circles(n)]
    return validate_data(Scenario, data, source="bench")


PHALANX = """
import json, sys, time
t0 = time.perf_counter()
from phalanx.core.config import Scenario
from phalanx.core.config_files import CONFIG_ROOT, load_scenario, validate_data
from phalanx.core.scenarios import grid_scenario
from phalanx.runtime.batch import BatchRunner
n, steps, circles = json.loads(sys.argv[1])
base = grid_scenario(load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml"), n)
data = base.model_dump()
data["duration_s"] = steps / base.control_rate_hz
data["world"]["circles"] = [{"x_m": x, "y_m": y, "radius_m": r} for x, y, r in circles]
runner = BatchRunner(validate_data(Scenario, data, source="bench"))
t1 = time.perf_counter()
runner.run()
t2 = time.perf_counter()
print(json.dumps({"setup_s": t1 - t0, "loop_s": t2 - t1, "steps": runner.steps}))
"""

IRSIM = """
import json, math, sys, time
t0 = time.perf_counter()
import irsim, yaml
n, steps, circles, folder = json.loads(sys.argv[1])
cols = max(1, math.ceil(math.sqrt(n)))
states = [[-(i // cols) * 2.0, -(i % cols) * 2.0, 0.0] for i in range(n)]
world = {
    "world": {"height": 200, "width": 400, "offset": [-150, -100], "step_time": 0.1,
              "sample_time": 0.1, "collision_mode": "stop", "control_mode": "auto"},
    "robot": [{"number": n, "distribution": {"name": "manual"}, "kinematics": {"name": "diff"},
               "shape": {"name": "circle", "radius": RADIUS}, "state": states,
               "goal": [[s[0] + 40.0, s[1], 0.0] for s in states], "behavior": {"name": "dash"},
               "vel_max": [0.3, 0.7],
               "sensors": [{"name": "lidar2d", "range_min": 0.02, "range_max": 5.0,
                            "angle_range": 6.2832, "number": 16}]}],
    "obstacle": [{"number": len(circles), "distribution": {"name": "manual"},
                  "shape": [{"name": "circle", "radius": r} for _, _, r in circles],
                  "state": [[x, y, 0.0] for x, y, _ in circles]}],
}
path = folder + "/world.yaml"
with open(path, "w") as f:
    yaml.safe_dump(world, f)
env = irsim.make(path, display=False, disable_all_plot=True, log_level="ERROR")
t1 = time.perf_counter()
for _ in range(steps):
    env.step()
t2 = time.perf_counter()
print(json.dumps({"setup_s": t1 - t0, "loop_s": t2 - t1, "steps": steps}))
""".replace("RADIUS", repr(RADIUS_M))


def compile_sources() -> None:
    """Byte-compile phalanx's sources, as installing a package does (IR-SIM's, installed
    from a wheel, are): every fresh process then reads bytecode instead of compiling
    the sources again, also where PYTHONDONTWRITEBYTECODE is set.
    """
    import phalanx

    root = Path(phalanx.__file__).resolve().parent
    for folder in (root, *(root / part for part in ("agents", "drivers", "simulator"))):
        compileall.compile_dir(folder.resolve(), quiet=1)  # (it skips the symlinks)


def run(
    code: str, args: list[object], *, env: dict[str, str] | None = None
) -> tuple[float, dict[str, Any]]:
    """(whole process wall s, what the child printed) of one fresh process running
    `code` with `args` as JSON in its argv[1] (and `env` as its environment, if given).
    """
    started = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-c", code, json.dumps(args)],
        check=True,
        capture_output=True,
        text=True,
        timeout=1800,
        env=env,
    )
    whole = time.perf_counter() - started
    return whole, json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--robots", type=int, nargs="+", default=sorted(STEPS))
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    try:
        import irsim  # noqa: F401
    except ImportError:
        print("IR-SIM is not installed: pip install -e '.[bench]'")
        return
    compile_sources()
    cal = Calibration.measure()
    print(
        "robots  steps  | loop s: irsim  phalanx  (cal)  | robot-steps/s: irsim  phalanx  "
        "x  | whole process s: irsim  phalanx  (cal)  x  | load"
    )
    with tempfile.TemporaryDirectory() as folder:
        for n in args.robots:
            steps = STEPS.get(n, 100)
            field = circles(n)
            ir, ph = [], []
            for _ in range(args.repeats):
                ir.append(run(IRSIM, [n, steps, field, folder]))
                ph.append(run(PHALANX, [n, steps, field]))
            ir_loop = statistics.median(r[1]["loop_s"] for r in ir)
            ph_loop = statistics.median(r[1]["loop_s"] for r in ph)
            ir_whole = statistics.median(r[0] for r in ir)
            ph_whole = statistics.median(r[0] for r in ph)
            rs = n * steps
            print(
                f"{n:6d}  {steps:5d}  | {ir_loop:11.2f}  {ph_loop:7.2f}  "
                f"({cal.ratio(ph_loop):5.0f})  "
                f"| {rs / ir_loop:18.0f}  {rs / ph_loop:7.0f}  {ir_loop / ph_loop:4.1f}  "
                f"| {ir_whole:20.2f}  {ph_whole:7.2f}  ({cal.ratio(ph_whole):5.0f})  "
                f"{ir_whole / ph_whole:4.1f}  | {load()}",
                flush=True,
            )
    Calibration.measure()


if __name__ == "__main__":
    main()
