"""The formation on real sensing: the paper scenario in its three formations with each
sensing set, a 20-minute run on relative markers, a run whose marker is hidden for 5 s,
the filter's honesty (NEES) and the estimator's cost per step.

Sensing sets (every robot runs the pose estimator; odometry errors as in
configs/scenarios/real_*.toml): odometry alone; + motion capture (100 Hz, 2 mm, 0.1 deg,
20 ms, 1 % dropouts); + relative markers (15 Hz, 2 % of range, 1 deg bearing, 1 deg
relative heading at 1 m, 90 deg field of view, 50 ms); both. Formation errors are the
paper's, on ground truth (the worst follower); estimation errors are each robot's
published pose against ground truth (the worst robot).

Prints the tables; with --write, rewrites the localisation part of docs/RESULTS.md.

    .venv/bin/python bench/bench_localisation.py --workers 2 --write
"""

from __future__ import annotations

import argparse
import math
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from calibration import Calibration

from phalanx.analysis.estimation import drift_cm_per_m, estimation_metrics, pose_errors
from phalanx.analysis.metrics import CORE_BOUNDS, error_series, is_follower, run_metrics
from phalanx.analysis.report import LOCALISATION_BEGIN, LOCALISATION_END, with_section, worst
from phalanx.core.config import Scenario
from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_scenario
from phalanx.core.runlog import RunLog
from phalanx.core.scenarios import signal_builder
from phalanx.runtime.batch import BatchRunner

REPO = Path(__file__).resolve().parent.parent
FORMATIONS = ("wedge", "inline", "collateral")
SETS = {
    "odometry": (False, False),
    "odometry + mocap": (True, False),
    "odometry + markers": (False, True),
    "both": (True, True),
}
PAPER_BOUNDS = (2.0, 0.8, 1.3)
ERROR_KEYS = ("linear_pct", "angular_pct", "orientation_deg")
BEGIN = LOCALISATION_BEGIN
END = LOCALISATION_END


def with_sources(scenario: Scenario, mocap: bool, markers: bool) -> Scenario:
    """`scenario` keeping only the positioning sources asked for."""
    loc = scenario.localisation.model_copy(
        update={
            "mocap": scenario.localisation.mocap if mocap else None,
            "markers": scenario.localisation.markers if markers else None,
        }
    )
    return scenario.model_copy(update={"localisation": loc})


def timed_run(scenario: Scenario) -> tuple[RunLog, list[float]]:
    """Run `scenario`; the wall time of every estimator step (s)."""
    runner = BatchRunner(scenario)
    times: list[float] = []
    for agent in runner.agents.values():
        estimator = agent.estimator
        if estimator is None:
            continue
        inner = estimator.step

        def step(*args: Any, _inner: Any = inner, **kwargs: Any) -> Any:
            started = time.perf_counter()
            out = _inner(*args, **kwargs)
            times.append(time.perf_counter() - started)
            return out

        estimator.step = step  # type: ignore[method-assign]
    return runner.run(), times


def sensing_study(name: str) -> Scenario:
    """Scenario `name` blocked at 100 s by the paper's signal builder instead of its wall:
    this studies the sensing, and a wall meets a group on poor sensing (odometry alone,
    0.5 m off its slots) robot by robot, never all at once.
    """
    scenario = load_scenario(CONFIG_ROOT / "scenarios" / f"{name}.toml")
    keep = tuple(e for e in scenario.events if e.kind != "all_sonars_blocked")
    return apply_overrides(scenario, signal_builder(100.0, keep=keep), source=name)


def matrix_run(job: tuple[str, str]) -> dict[str, Any]:
    """One formation with one sensing set: formation and estimation figures, cost."""
    form, name = job
    base = sensing_study(f"real_{form}")
    log, times = timed_run(with_sources(base, *SETS[name]))
    metrics = run_metrics(log)
    est = metrics["estimation"]
    robots = est["robots"].values()
    return {
        "formation": form,
        "set": name,
        "backward": [worst(metrics, "backward", k) for k in ERROR_KEYS],
        "forward_linear_pct": worst(metrics, "forward", "linear_pct"),
        "est_m": max(r["position_m"]["max"] for r in robots),
        "est_deg": max(r["heading_deg"]["max"] for r in robots),
        "drift_cm_per_m": max(drift_cm_per_m(log, rid) for rid in log.traces),
        "nees_in_band": est["nees_in_band"],
        "collisions": len({(c.t_s, *sorted((c.robot_id, c.other))) for c in log.collisions}),
        "leaders": sorted({state for tr in log.traces.values() for state in tr.leaders}),
        "cost_us": 1e6 * np.asarray(times),
    }


def window_max(log: RunLog, start_s: float, end_s: float) -> list[float]:
    """The worst follower's max linear %, angular %, orientation deg in [start, end)."""
    mask = (log.t_s >= start_s) & (log.t_s < end_s)
    out = [0.0, 0.0, 0.0]
    for rid in (r for r in log.formation.robot_ids if is_follower(log, r)):
        series = error_series(log, rid)
        for i, key in enumerate(ERROR_KEYS):
            values = getattr(series, key)[mask]
            values = values[np.isfinite(values)]
            if values.size:
                out[i] = max(out[i], float(values.max()))
    return out


def minute_rms(log: RunLog, start_s: float) -> list[float]:
    """The worst follower's RMS linear %, angular %, orientation deg over one minute."""
    mask = (log.t_s >= start_s) & (log.t_s < start_s + 60.0)
    out = [0.0, 0.0, 0.0]
    for rid in (r for r in log.formation.robot_ids if is_follower(log, r)):
        series = error_series(log, rid)
        for i, key in enumerate(ERROR_KEYS):
            values = getattr(series, key)[mask]
            values = values[np.isfinite(values)]
            if values.size:
                out[i] = max(out[i], float(np.sqrt(np.mean(values**2))))
    return out


def long_run(_: object = None) -> dict[str, Any]:
    """20 minutes on markers: every minute's errors; the second against the last."""
    scenario = load_scenario(CONFIG_ROOT / "scenarios" / "real_wedge_markers_long.toml")
    log, _times = timed_run(scenario)
    minutes = int(scenario.duration_s // 60)
    rms = [minute_rms(log, 60.0 * m) for m in range(minutes)]
    linear = np.array([r[0] for r in rms[1:]])  # from the second minute (the first converges)
    slope = float(np.polyfit(np.arange(2, minutes + 1), linear, 1)[0])
    est = estimation_metrics(log)
    return {
        "second": window_max(log, 60.0, 120.0),
        "last": window_max(log, 60.0 * (minutes - 1), 60.0 * minutes),
        "rms": rms,
        "slope_pct_per_min": slope,
        "leader_drift_m": est["robots"][log.formation.root]["final_position_m"],
        "nees_in_band": est["nees_in_band"],
        "collisions": len(log.collisions),
    }


def hidden_run(_: object = None) -> dict[str, Any]:
    """The marker hidden 5 s: errors before, while hidden, after; when it is back."""
    scenario = sensing_study("real_wedge_marker_hidden")
    log, _times = timed_run(scenario)
    event = next(e for e in scenario.events if e.kind == "markers_hidden")
    start, end = event.start_s, event.start_s + event.duration_s
    robot = event.robots[0]
    series = error_series(log, robot)
    before = window_max(log, start - 10.0, start)
    lin = series.linear_pct
    after = np.flatnonzero((log.t_s >= end) & (lin <= max(before[0], 1e-9)))
    est = pose_errors(log.traces[robot])[0]
    return {
        "robot": robot,
        "window": (start, end),
        "before": before,
        "hidden": window_max(log, start, end),
        "after": window_max(log, end, end + 10.0),
        "back_s": float(log.t_s[after[0]] - end) if after.size else math.nan,
        "est_growth_m": float(
            est[(log.t_s >= start) & (log.t_s < end)].max() - est[log.t_s < start][-1]
        ),
        "collisions": len(log.collisions),
    }


def _mark(value: float, bound: float | None) -> str:
    if math.isnan(value):
        return "n/a"
    text = f"{value:.3g}"
    if bound is not None:
        text += " ✓" if value < bound else " ✗"
    return text


def matrix_table(rows: list[dict[str, Any]]) -> list[str]:
    """Markdown rows of the sensing matrix."""
    out = [
        "| formation | sensing | backward linear max % | backward angular max % "
        "| backward orientation max deg | forward linear max % | estimation error max "
        "(m / deg) | odometry drift cm/m | NEES in band | collisions |",
        "|---|---|---|---|---|---|---|---|---:|---:|",
    ]
    for r in rows:
        bounds = (
            tuple(CORE_BOUNDS[k] for k in ERROR_KEYS)
            if "mocap" in r["set"] or r["set"] == "both"
            else PAPER_BOUNDS
            if "markers" in r["set"]
            else (None, None, None)
        )
        cells = " | ".join(_mark(v, b) for v, b in zip(r["backward"], bounds, strict=True))
        drift = f"{r['drift_cm_per_m']:.2g}" if r["set"] == "odometry" else "-"
        out.append(
            f"| {r['formation']} | {r['set']} | {cells} | {r['forward_linear_pct']:.3g} "
            f"| {r['est_m']:.3g} / {r['est_deg']:.3g} | {drift} "
            f"| {100 * r['nees_in_band']:.1f} % | {r['collisions']} |"
        )
    return out


def cost_table(rows: list[dict[str, Any]], cal: Calibration) -> list[str]:
    """Estimator cost per step by sensing set, all formations and robots pooled; each
    figure also in micro-cal (millionths of the calibration workload).
    """
    out = ["| sensing | steps | p50 µs (micro-cal) | p99 µs (micro-cal) |", "|---|---:|---:|---:|"]
    for name in SETS:
        costs = np.concatenate([r["cost_us"] for r in rows if r["set"] == name])
        p50, p99 = np.percentile(costs, [50, 99])
        u50, u99 = (1e6 * cal.ratio(us * 1e-6) for us in (p50, p99))
        out.append(f"| {name} | {costs.size} | {p50:.0f} ({u50:.0f}) | {p99:.0f} ({u99:.0f}) |")
    return out


def _compare_minutes(long: dict[str, Any]) -> str:
    """Whether the last minute's errors are larger than the second's, said as it is."""
    second, last = long["second"][0], long["last"][0]
    rms = [r[0] for r in long["rms"][1:]]
    if last <= second and rms[-1] <= rms[0]:
        return "The last minute's linear errors are no larger than the second's. "
    return (
        f"The last minute's linear errors are a little above the second's (max {last:.2f} "
        f"against {second:.2f} %, RMS {rms[-1]:.2f} against {rms[0]:.2f} %), inside the "
        f"scatter from minute to minute (RMS {min(rms):.2f}-{max(rms):.2f} %). "
    )


def _triple(values: list[float]) -> str:
    return f"{values[0]:.3g} % / {values[1]:.3g} % / {values[2]:.3g} deg"


def section(rows: list[dict[str, Any]], long: dict[str, Any], hidden: dict[str, Any]) -> str:
    """The localisation part of docs/RESULTS.md, markers included."""
    lines = [
        BEGIN,
        "## Formation on real sensing: pose estimation, motion capture, relative markers",
        "",
        "Reproduce with `.venv/bin/python bench/bench_localisation.py --workers 2 --write` "
        "(rewrites this section; `phalanx report` keeps it). The paper scenario "
        "(`configs/scenarios/real_{wedge,inline,collateral}.toml`: the paper's run, the "
        "`ours` controller, every robot blocked at 100 s by the paper's signal builder in "
        "place of the scenario's wall: a wall meets a group on poor sensing robot by robot, "
        "never all at once) with every robot running its pose estimator and steering from "
        "its estimate. Odometry errors per wheel: a scale error drawn once per robot "
        "(0.1 % std), a random walk (1 mm after 1 m), a slip every 50 m a wheel rolls "
        "(losing up to 30 % of that step's travel). Motion capture: 100 Hz, 2 mm, 0.1 deg, "
        "20 ms latency, 1 % of frames lost, fused at 50 Hz, each fix at its own time. Markers: a "
        "camera on each follower aimed at the robot it follows, 15 Hz, 50 ms latency, "
        "2 % of range, 1 deg bearing, 1 deg relative heading at 1 m (growing with range), "
        "90 deg field of view, robots and obstacles occlude. Formation errors are the "
        "paper's on ground truth (worst follower, backward phase from 5 s after the switch); "
        "✓/✗ against the targets: with motion capture those of perfect sensing (< 0.5 % "
        "linear, < 0.3 % angular, < 0.5 deg orientation), with markers alone the paper's "
        "(< 2 %, < 0.8 %, < 1.3 deg). *Estimation error*: the worst robot's published pose "
        "against ground truth after 30 s. *Odometry drift*: the worst robot's final position "
        "error per metre it drove. *NEES in band*: the share of robot-steps (after 30 s) "
        "whose normalised estimation error squared lies inside the 95 % chi-square band "
        "(0.216-9.35, 3 degrees of freedom): about 95 % for an honest filter.",
        "",
        *matrix_table(rows),
        "",
        "### 20 minutes on relative markers",
        "",
        "`configs/scenarios/real_wedge_markers_long.toml`: the wedge driving forwards for "
        "20 minutes, one minute's weave (straight, left, straight, right at 3 deg/s) over "
        "and over, so every minute drives the same; the leader on odometry alone, the "
        "followers on odometry and markers. Worst follower, linear % / angular % / "
        "orientation deg (the orientation's maxima are the rigid-body heading's jumps when "
        "the leader's yaw rate steps, the same every minute):",
        "",
        "| minute | max | RMS |",
        "|---|---|---|",
        f"| 2nd (60-120 s) | {_triple(long['second'])} | {_triple(long['rms'][1])} |",
        f"| 20th (1140-1200 s) | {_triple(long['last'])} | {_triple(long['rms'][-1])} |",
        "",
        "RMS linear error, minutes 2 to 20: "
        + ", ".join(f"{r[0]:.2f}" for r in long["rms"][1:])
        + f" % (least-squares trend {long['slope_pct_per_min']:+.4f} % per minute). "
        + _compare_minutes(long)
        + f"The leader's own estimate ends {long['leader_drift_m']:.1f} m from the truth "
        "(odometry alone over 180 m); its followers keep their slots in its frame, so the "
        "formation does not drift with it. NEES in band over the run: "
        f"{100 * long['nees_in_band']:.0f} % (see the notes); collisions: "
        f"{long['collisions']}.",
        "",
        "### The marker hidden for 5 s",
        "",
        f"`configs/scenarios/real_wedge_marker_hidden.toml`: {hidden['robot']}'s camera sees "
        f"nothing from t = {hidden['window'][0]:.0f} to {hidden['window'][1]:.0f} s while the "
        "wedge turns at 3 deg/s; it coasts on its odometry (its estimate's error grows by "
        f"{1000 * hidden['est_growth_m']:.1f} mm). Its max errors (linear / angular / "
        "orientation):",
        "",
        "| when | errors |",
        "|---|---|",
        f"| the 10 s before | {_triple(hidden['before'])} |",
        f"| hidden | {_triple(hidden['hidden'])} |",
        f"| the 10 s after | {_triple(hidden['after'])} |",
        "",
        f"Collisions: {hidden['collisions']}.",
        "",
        *NOTES,
        "",
        END,
    ]
    return "\n".join(lines)


NOTES = [
    "- **Odometry alone**: each robot dead-reckons on its own, its wheels' scale errors "
    "turning its heading by a few degrees over the run, so the robots' frames drift "
    "apart: the formation, measured on ground truth, is lost within the run (tens of "
    "per cent; in the wedge and the collateral line two robots touch and the lead passes "
    "after the contact). The drift column is the worst robot's final position error per "
    "metre it drove. The filter is honest about it: the wheels' scale errors are consider "
    "parameters (`phalanx.agents.estimation.ekf`), so its covariance grows as the real "
    "error does (NEES inside the band at every step).",
    "- **With motion capture** every robot knows its pose in the world within 2 mm and a "
    "third of a degree, and the formation keeps the bounds of perfect sensing. What is "
    "left is the leader's heading noise times the slot's lever arm: 0.36 deg for the "
    "inline formation's last robot, 2 m behind (at 0.2 deg of motion-capture heading "
    "noise instead of 0.1 it was 0.64 deg, over the bound). Fixes are fused at 50 Hz "
    "(`fuse_hz`; 100 Hz, every fix, gives errors within 0.05 deg of these and costs "
    "about 1.6 times as much, docs/PERFORMANCE.md). *Both*: a robot with fresh fixes "
    "stays in the world frame and leaves its markers aside, so the rows equal motion "
    "capture's.",
    "- **With markers alone** a follower's estimate lives in the frame of the robot it "
    "measures: it keeps its slot relative to that robot whatever the leader's odometry "
    "does in the world (the estimation error against the world is the leader's odometry "
    "drift; the formation error is not). Linear and angular errors are inside the "
    "paper's bounds in every formation, the orientation in the wedge and the collateral "
    "line but not for the inline formation's last robot (2.73 deg), which tracks the "
    "leader 2 m ahead but can only see the middle robot (the leader is behind it) and so "
    "keeps its slot in that robot's estimate, itself built from markers. What we "
    "measured and what did not help: 0.2 deg of bearing noise instead of 1 (2.6 deg), "
    "0.3 deg of relative heading noise (2.36 deg), a control point 0.3 or 0.5 m from the "
    "axle (2.73, 2.41 deg), the leader visible over the middle robot and fused alone (a "
    "marker on a mast: 2.21 deg). The mechanism is a lateral estimate that wanders by a "
    "few millimetres a second, which a robot reversing at 0.15 m/s follows with a "
    "heading offset of a degree or two; what would remove it for the chain we have not "
    "established. (An earlier simulated camera took each frame from the poses at the end "
    "of the world's 25 ms sub-step instead of the frame's own instant: the wedge then "
    "gave 1.48 deg, over the bound, the chain the same 2.73.)",
    "- **Honesty over 20 minutes**: the NEES band holds in the 200 s runs (95.7-100 % of "
    "steps), not over the 20-minute run (see its section): past about five minutes on "
    "odometry alone the leader's heading is more than 10 deg off, and a covariance "
    "linearised about the estimate no longer describes an error that lies along an arc "
    "(the extended Kalman filter's known limit); the published covariance is then too "
    "small across the arc. The formation does not suffer: the followers' slots are "
    "relative to the leader's estimate.",
]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--formations", nargs="+", default=list(FORMATIONS))
    parser.add_argument("--write", action="store_true", help="rewrite docs/RESULTS.md's part")
    args = parser.parse_args()
    jobs = [(form, name) for form in args.formations for name in SETS]
    cal = Calibration.measure()
    started = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        long_future = pool.submit(long_run)
        hidden_future = pool.submit(hidden_run)
        rows = list(pool.map(matrix_run, jobs))
        long, hidden = long_future.result(), hidden_future.result()
    print(f"{len(jobs) + 2} runs in {time.perf_counter() - started:.0f} s wall")
    print("\n".join(matrix_table(rows)))
    print()
    print("\n".join(cost_table(rows, cal)))
    Calibration.measure()
    print()
    print("long:", long)
    print("hidden:", hidden)
    if args.write:
        path = REPO / "docs" / "RESULTS.md"
        text = section(rows, long, hidden)
        path.write_text(
            with_section(path.read_text(encoding="utf-8"), text, begin=BEGIN, end=END),
            encoding="utf-8",
        )
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
