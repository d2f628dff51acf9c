"""The paper's scenarios on AMRISim's P3DXs against the same scenarios in phalanx's own
simulator: the formation errors on AMRISim's true poses, and how far each robot's path on
AMRISim is from its path in phalanx's simulator, step by step: with ideal robots, and
with robots whose firmware is as late as AMRISim's (FIRMWARE: commands acted on 0.1 s
late, sonar read 0.2 s late).

    PHALANX_AMRISIM=/path/to/AMRISim .venv/bin/python bench/bench_amrisim.py [--write]

Each scenario runs once on AMRISim (`phalanx up SCENARIO --robots amrisim`, real time:
200 s each) and once in process (`phalanx run`). `--write` puts the table into
docs/ROBOTS.md. `--prefix real` runs the real-sensing scenarios (estimator on) instead,
with `--odometry-error` for AMRISim's own odometry error model.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from phalanx.analysis.report import with_section, worst
from phalanx.analysis.results import read_traces

REPO = Path(__file__).resolve().parent.parent
SCENARIOS = REPO / "configs" / "scenarios"
DOC = REPO / "docs" / "ROBOTS.md"
BEGIN = "<!-- amrisim benchmark: written by bench/bench_amrisim.py -->"
END = "<!-- end of amrisim benchmark -->"
KEYS = ("linear_pct", "angular_pct", "orientation_deg")
FIRMWARE = ("world.command_delay_s=0.1", "world.sonar_delay_s=0.2")


def run(argv: list[str], timeout_s: float) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "phalanx", *argv],
        capture_output=True, text=True, timeout=timeout_s, check=False,
    )  # fmt: skip
    if proc.returncode != 0:
        sys.stderr.write(proc.stderr[-3000:])
        raise SystemExit(f"phalanx {' '.join(argv[:2])} failed ({proc.returncode})")


def path_gap(a: dict[str, Any], b: dict[str, Any]) -> tuple[float, float, float]:
    """Over every robot: the RMS and the max of the distance between its two paths at
    every step (m), and when the max was (s).
    """
    t = a[""]["t_s"]
    gaps = [np.hypot(a[r]["x_m"] - b[r]["x_m"], a[r]["y_m"] - b[r]["y_m"]) for r in a if r]
    stacked = np.vstack(gaps)
    k = int(np.argmax(stacked.max(axis=0)))
    return float(np.sqrt(np.mean(stacked**2))), float(stacked.max()), float(t[k])


def measure(name: str, out: Path, sets: list[str], odometry_error: str) -> dict[str, Any]:
    scenario = SCENARIOS / f"{name}.toml"
    extra = [arg for s in sets for arg in ("--set", s)]
    amrisim = out / f"{name}-amrisim"
    on_amrisim = ["--robots", "amrisim", "--amrisim-odometry-error", odometry_error]
    run(["up", str(scenario), *on_amrisim, "--out", str(amrisim), "--no-recording",
         "--timeout", "900", *extra], 1200.0)  # fmt: skip
    metrics = json.loads((amrisim / "metrics.json").read_text())
    robots = read_traces(amrisim / "traces.npz")
    gaps = []
    for label, model in (("phalanx", ()), ("phalanx-late", FIRMWARE)):
        sim = out / f"{name}-{label}"
        late = [arg for s in model for arg in ("--set", s)]
        run(["run", str(scenario), "--out", str(sim), "--no-recording", *extra, *late], 600.0)
        gaps.append(path_gap(robots, read_traces(sim / "traces.npz")))
    runtime = metrics["runtime"]
    rates = runtime.get("simulator_clock_rate", {}).values()
    return {
        "name": name,
        "complete": metrics["complete"],
        "steps": min(a["steps"] for a in runtime["agents"].values()),
        "reverses": metrics["deadlock_reverses"],
        "backward": [worst(metrics, "backward", k) for k in KEYS],
        "forward": [worst(metrics, "forward", k) for k in KEYS],
        "steady": [worst(metrics, "forward_steady", k) for k in KEYS],
        "gaps": gaps,
        "clock": min(rates, default=float("nan")),
        "collisions": len(metrics["collisions"]),
    }


def table(rows: list[dict[str, Any]]) -> list[str]:
    fmt = "/".join
    lines = [
        "| scenario | backward max % / % / deg | forward max % / % / deg | forward steady max "
        "% / % / deg | reverses | path gap to phalanx's sim, ideal robots: RMS / max (at) "
        "| ... robots as late as AMRISim's | AMRISim clock | steps run | complete "
        "| collisions |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        gaps = " | ".join(
            f"{100 * rms_m:.1f} cm / {100 * max_m:.1f} cm ({at_s:.0f} s)"
            for rms_m, max_m, at_s in r["gaps"]
        )
        lines.append(
            f"| {r['name']} | {fmt(f'{v:.3g}' for v in r['backward'])} "
            f"| {fmt(f'{v:.3g}' for v in r['forward'])} | {fmt(f'{v:.3g}' for v in r['steady'])} "
            f"| {r['reverses']} | {gaps} | {r['clock']:.4f} | {r['steps']} | {r['complete']} "
            f"| {r['collisions']} |"
        )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--prefix", default="paper", choices=("paper", "real"))
    parser.add_argument("--shape", action="append", choices=("wedge", "inline", "collateral"))
    parser.add_argument("--odometry-error", default="none")
    parser.add_argument("--set", action="append", default=[], dest="sets")
    parser.add_argument("--out", type=Path, default=REPO / "results" / "bench-amrisim")
    parser.add_argument("--write", action="store_true", help=f"into {DOC.relative_to(REPO)}")
    args = parser.parse_args()
    rows = [
        measure(f"{args.prefix}_{shape}", args.out, args.sets, args.odometry_error)
        for shape in args.shape or ("wedge", "inline", "collateral")
    ]
    lines = table(rows)
    print("\n".join(lines))
    if args.write:
        command = " ".join(["bench/bench_amrisim.py", *sys.argv[1:]])
        section = "\n".join([BEGIN, "", f"`{command}`:", "", *lines, "", END])
        DOC.write_text(with_section(DOC.read_text(), section, begin=BEGIN, end=END))


if __name__ == "__main__":
    main()
