"""Navigation Monte-Carlo: every formation through many seeded obstacle fields, and the
U-shaped dead end escaped in reverse.

For each shape (wedge, inline, collateral) and each seed, `navigation_scenario("field",
shape, robots, seed=seed)` (the scenario of configs/scenarios/nav_field_*.toml with that
field seed) runs in the batch runner until the goal is reached or the group is STUCK (plus
10 s for the followers to settle), at most its 240 s. Worker processes share the seeds.
Then configs/scenarios/nav_deadend_wedge3.toml (and inline, collateral) runs to the end
and its backward phase is measured against the formation-core bounds.

Prints the tables; with --write, rewrites the navigation part of docs/RESULTS.md and
docs/figures/deadend-*.png.

    .venv/bin/python bench/bench_montecarlo.py --seeds 100 --workers 2 --write
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

from phalanx.analysis.metrics import (
    CORE_BOUNDS,
    error_series,
    is_follower,
    navigation_metrics,
    phase_masks,
)
from phalanx.analysis.report import SECTION_BEGIN, SECTION_END, with_section
from phalanx.analysis.sweep import run_until_done
from phalanx.analysis.sweep import summarise as sweep_summary
from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.core.runlog import RunLog
from phalanx.core.scenarios import SHAPES, navigation_scenario
from phalanx.runtime.batch import BatchRunner

REPO = Path(__file__).resolve().parent.parent


def field_run(job: tuple[str, int, int]) -> dict[str, Any]:
    """One seeded field: its navigation metrics and wall time."""
    shape, robots, seed = job
    started = time.perf_counter()
    log = run_until_done(BatchRunner(navigation_scenario("field", shape, robots, seed=seed)))
    nav = navigation_metrics(log)
    return {"shape": shape, "robots": robots, "seed": seed, "wall_s": time.perf_counter() - started,
            **nav}  # fmt: skip


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Aggregate the runs of one shape: `phalanx sweep`'s summary (the same numbers), and
    the runs with a collision of any kind, which only this table shows.
    """
    summary = sweep_summary(rows)
    summary["runs_with_collision"] = sum(
        1 for r in rows if r["collisions_obstacle"] or r["collisions_robot"]
    )
    return summary


def deadend_run(shape: str, robots: int = 3) -> tuple[RunLog, dict[str, Any]]:
    """The dead end (`nav_deadend_{shape}{robots}.toml`) to the end: backward-phase errors
    of every follower (after settle_s).
    """
    scenario = load_scenario(CONFIG_ROOT / "scenarios" / f"nav_deadend_{shape}{robots}.toml")
    log = run_until_done(BatchRunner(scenario))
    _, backward = phase_masks(log)
    worst = dict.fromkeys(CORE_BOUNDS, 0.0)
    seconds = float(backward.sum()) * scenario.dt_s
    for rid in (r for r in log.formation.robot_ids if is_follower(log, r)):
        series = error_series(log, rid)
        mask = backward & np.isfinite(series.linear_pct)
        for k in CORE_BOUNDS:
            values = getattr(series, k)[mask]
            if values.size:
                worst[k] = max(worst[k], float(values.max()))
    nav = navigation_metrics(log)
    return log, {"shape": shape, "backward_s": seconds, "worst": worst, **nav}


def _fmt(value: float, digits: int = 3) -> str:
    return "n/a" if not math.isfinite(value) else f"{value:.{digits}g}"


def field_table(summaries: dict[str, dict[str, Any]]) -> list[str]:
    """Markdown: one row per shape."""
    rows = [
        "| formation | runs | goal reached | stuck | collisions robot-obstacle / robot-robot "
        "| deadlock reverses (runs) | leadership changes | time to goal mean / median / max "
        "| calm linear % mean / max | calm angular % mean / max | calm orientation deg "
        "mean / max | calm linear m mean / max | time in episodes |",
        "|---|---:|---:|---:|---|---|---:|---|---|---|---|---|---:|",
    ]
    for shape, s in summaries.items():
        c = s["calm"]
        rows.append(
            f"| {shape} | {s['runs']} | {100 * s['reached'] / s['runs']:.0f} % "
            f"| {s['stuck']} | {s['obstacle_collisions']} / {s['robot_collisions']} "
            f"| {s['deadlock_reverses']} ({s['runs_with_reverse']}) | {s['leadership_changes']} "
            f"| {_fmt(s['time_mean_s'])} / {_fmt(s['time_median_s'])} / "
            f"{_fmt(s['time_max_s'])} s "
            f"| {_fmt(c['linear_pct']['mean'])} / {_fmt(c['linear_pct']['max'])} "
            f"| {_fmt(c['angular_pct']['mean'])} / {_fmt(c['angular_pct']['max'])} "
            f"| {_fmt(c['orientation_deg']['mean'])} / {_fmt(c['orientation_deg']['max'])} "
            f"| {_fmt(c['linear_m']['mean'])} / {_fmt(c['linear_m']['max'])} "
            f"| {100 * s['episode_share']:.0f} % |"
        )
    return rows


def deadend_table(results: list[dict[str, Any]]) -> list[str]:
    """Markdown: the dead end per shape, backward phase against the core bounds."""
    rows = [
        "| formation | deadlock reverses | measured reverse | backward linear max % "
        "| backward angular max % | backward orientation max deg | goal reached "
        "| collisions |",
        "|---|---:|---:|---|---|---|---|---:|",
    ]
    for r in results:
        w = r["worst"]
        marks = {k: " ✗" if w[k] > b else " ✓" for k, b in CORE_BOUNDS.items()}
        measured = r["backward_s"] > 0
        rows.append(
            f"| {r['shape']} | {r['deadlock_reverses']} | {r['backward_s']:.0f} s "
            + "".join(f"| {_fmt(w[k]) + marks[k] if measured else 'n/a'} " for k in CORE_BOUNDS)
            + f"| {'yes' if r['goal_reached'] else 'no'} "
            f"| {r['collisions_obstacle'] + r['collisions_robot']} |"
        )
    return rows


def section(
    seeds: int,
    robots: int,
    summaries: dict[str, dict[str, Any]],
    deadends: list[dict[str, Any]],
    figure: str,
) -> str:
    """The navigation part of docs/RESULTS.md."""
    lines = [
        SECTION_BEGIN,
        "## Navigation: seeded obstacle fields and the dead end",
        "",
        "Reproduce with `.venv/bin/python bench/bench_montecarlo.py --seeds "
        f"{seeds} --robots {robots} --workers 2 --write` (rewrites this section and "
        "`docs/figures/deadend-*.png`; `phalanx report` keeps it).",
        "",
        f"### {seeds} seeded obstacle fields per formation ({robots} robots)",
        "",
        'Each run: `navigation_scenario("field", shape, '
        f"{robots}, seed=s)` for s = 0..{seeds - 1} (the scenario of "
        "`configs/scenarios/nav_field_*.toml`): 18 round obstacles (0.2-0.45 m, at least "
        "1.2 m apart) scattered between start and goal 24 m away in a 12 m wide arena, the "
        "leader navigating on sonar alone (reactive steering over a map it builds), followers "
        "in formation with `ours`, |v| <= 0.3 m/s, |omega| <= 40 deg/s, at most 240 s. "
        "Collisions count contact episodes (ground truth). *Calm* errors are the paper's "
        "formation errors (against the robot each follower tracks, all followers' steps "
        "pooled) outside obstacle-avoidance episodes: an episode runs from a robot leaving "
        "its slot (AVOID, EMERGENCY_STOP, HOLD, JOIN, STUCK) until it is back in it "
        "(within 0.1 m, or a tenth of its slot's distance from the leader if more, and "
        "15 deg), or while the leader turns the shape on the spot or "
        "away from a dead end (DEADLOCK_TURN), and `settle_s` = 5 s after; the deadlock "
        "reverse itself is measured. *Time in episodes* is the share of steps excluded "
        "that way. A run that does not reach the goal ran out of its 240 s or ended STUCK "
        "(deadlock retries used up).",
        "",
        *field_table(summaries),
        "",
        "### The U-shaped dead end, escaped in reverse",
        "",
        "`configs/scenarios/nav_deadend_*3.toml`: a U 1.2 m wider than the shape, 8 m deep "
        "(its end out of sonar range from the mouth), the goal behind it. The group drives "
        "in; once the leader's map shows its route leading back the way it came and no room "
        "to turn the shape round, the group is in deadlock: it turns the shape back to the "
        "way it came in (the heading of the leader's last 2 m of path: a leader caught "
        "turning would otherwise back out diagonally), stands still 12 s "
        "(`deadlock.pause_s`: the followers settle onto their slots, position then "
        "heading), backs out straight in "
        "formation (`deadlock.reverse_mode = 'fixed'`, as the paper) for 10 m, turns "
        "towards the route and goes round. Backward-phase errors are measured from 5 s "
        "after the reverse starts (the formation-core convention), against the "
        "formation-core bounds (< 0.5 % linear, < 0.3 % angular, < 0.5 deg orientation).",
        "",
        *deadend_table(deadends),
        "",
        *DEADEND_NOTES,
        "",
        f"![dead end, wedge]({figure})",
        "",
        SECTION_END,
    ]
    return "\n".join(lines)


DEADEND_NOTES = [
    "- **Every formation of three backs out within the bounds and reaches the goal**: the "
    "wedge and the line abreast fold into a column on the way in, the turn back swings "
    "the column's slots about 0.1 m sideways, and the followers settle onto their slots "
    "(a turn, a straight drive, a turn on the spot) before the reverse starts. The chain "
    "drives in because a dead end needs its route to lead back two re-plans running (the "
    "sonar's arcs close and open the U's mouth on the map from one re-plan to the next).",
    "- **5 robots** (`nav_deadend_*5.toml`, not in the table): the chain backs out within "
    "the bounds three times and runs out of time; the wedge reaches the goal after a "
    "reverse an obstacle stopped at 0.08 m (it turns round inside the U instead); the "
    "line abreast backs out within the linear and angular bounds (0.0201 %, 0.0409 %), "
    "0.731 deg of orientation (the fourth robot against the second, whose own small turn "
    "tilts the reference), and does not reach the goal. No collision.",
]


def main() -> None:
    Calibration.measure()  # (the unit every time below can be divided by, on any machine)
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=100)
    parser.add_argument("--robots", type=int, default=3)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--shapes", nargs="+", default=list(SHAPES))
    parser.add_argument("--write", action="store_true", help="rewrite docs/RESULTS.md's part")
    args = parser.parse_args()
    jobs = [(shape, args.robots, seed) for shape in args.shapes for seed in range(args.seeds)]
    started = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        rows = list(pool.map(field_run, jobs, chunksize=2))
        deadends_out = list(pool.map(deadend_run, args.shapes))
    summaries = {s: summarise([r for r in rows if r["shape"] == s]) for s in args.shapes}
    deadends = [d for _, d in deadends_out]
    print(f"{len(jobs)} field runs in {time.perf_counter() - started:.0f} s wall")
    print("\n".join(field_table(summaries)))
    print()
    print("\n".join(deadend_table(deadends)))
    for s in summaries:
        failed = [r["seed"] for r in rows if r["shape"] == s and not r["goal_reached"]]
        print(f"{s}: seeds not reaching the goal: {failed}")
    if args.write:
        from phalanx.analysis.figures import deadend_escape, save_figure, states

        figures = REPO / "docs" / "figures"
        wedge = next(log for log, d in deadends_out if d["shape"] == "wedge")
        save_figure(deadend_escape(wedge), figures / "deadend-wedge3-escape.png")
        save_figure(states(wedge), figures / "deadend-wedge3-fig4b_states.png")
        path = REPO / "docs" / "RESULTS.md"
        text = section(args.seeds, args.robots, summaries, deadends,
                       "figures/deadend-wedge3-escape.png")  # fmt: skip
        path.write_text(with_section(path.read_text(encoding="utf-8"), text), encoding="utf-8")
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
