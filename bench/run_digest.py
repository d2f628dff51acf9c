"""A digest of in-process runs, to show a speed change leaves every result as it was.

Runs the IR-SIM benchmark's grids (3, 10, 100 and 300 robots among its circles), the
paper wedge and line, and a field, a dead end, a narrow passage and a corridor (their
first 80 s) with `BatchRunner`, and prints one hash per run over every robot's trace
(ground truth, commands, direction), states, tracked and formation leaders, formed
flags, and the run's transitions and collisions. Run it before and after a change and
compare the two outputs: any difference in any bit of any of them changes its line.

    .venv/bin/python bench/run_digest.py > before.txt   # ... change ...
    .venv/bin/python bench/run_digest.py | diff before.txt -
"""

from __future__ import annotations

import hashlib

import numpy as np
from bench_vs_irsim import phalanx_scenario

from phalanx.core.config import Scenario
from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.core.runlog import RunLog
from phalanx.runtime.batch import BatchRunner

GRIDS = ((3, 600), (10, 400), (100, 100), (300, 30))  # (robots, steps)
FILES = (
    "paper_wedge",
    "paper_inline",
    "nav_field_wedge5",
    "nav_deadend_inline3",
    "nav_narrow_collateral5",
    "nav_corridor_wedge3",
)
NAV_S = 80.0  # the navigation scenarios' first seconds


def cases() -> dict[str, Scenario]:
    """Every run the digest covers, by name."""
    runs = {f"grid{n}": phalanx_scenario(n, steps) for n, steps in GRIDS}
    for name in FILES:
        scenario = load_scenario(CONFIG_ROOT / "scenarios" / f"{name}.toml")
        if name.startswith("nav"):
            scenario = scenario.model_copy(update={"duration_s": min(scenario.duration_s, NAV_S)})
        runs[name] = scenario
    return runs


def digest(log: RunLog) -> str:
    """A hash of everything the run recorded that results are made of."""
    h = hashlib.sha256()
    for trace in log.traces.values():
        for column in (
            trace.x_m,
            trace.y_m,
            trace.theta_rad,
            trace.v_mps,
            trace.omega_radps,
            trace.cmd_v_mps,
            trace.cmd_omega_radps,
            trace.direction,
        ):
            h.update(np.ascontiguousarray(column).tobytes())
        h.update(repr((trace.states, trace.tracked, trace.leaders, trace.formed)).encode())
    h.update(repr(log.transitions).encode())
    h.update(repr(log.collisions).encode())
    return h.hexdigest()[:16]


def main() -> None:
    for name, scenario in cases().items():
        print(name, digest(BatchRunner(scenario).run()), flush=True)


if __name__ == "__main__":
    main()
