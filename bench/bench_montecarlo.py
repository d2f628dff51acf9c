"""Navigation: the U-shaped dead end escaped in reverse, and (on request) the formations
through many seeded obstacle fields.

configs/scenarios/nav_deadend_{wedge,inline,collateral}{3,5}.toml each run in the batch
runner until the goal is reached or the group is STUCK (plus 10 s for the followers to
settle), and the backward phase is measured against the formation-core bounds. With
`--seeds N`, for each shape, group size and seed, `navigation_scenario("field", shape,
robots, seed=seed)` (the scenario of configs/scenarios/nav_field_*.toml with that field
seed) runs the same way; worker processes share the runs.

Prints the tables; with --write, rewrites the navigation part of docs/RESULTS.md (the
dead end's table, its notes and figures, docs/figures/deadend-*.png). The seeded fields'
table is printed only: `phalanx sweep --write` writes theirs, the section after it.

    .venv/bin/python bench/bench_montecarlo.py --workers 2 --write
    .venv/bin/python bench/bench_montecarlo.py --seeds 100 --robots 3   # + 300 field runs
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
    leader_direction,
    navigation_metrics,
    phase_masks,
)
from phalanx.analysis.report import SECTION_BEGIN, SECTION_END, with_section
from phalanx.analysis.sweep import run_until_done
from phalanx.analysis.sweep import summarise as sweep_summary
from phalanx.core.config_files import CONFIG_ROOT, load_scenario
from phalanx.core.runlog import RunLog
from phalanx.core.scenarios import SHAPES, navigation_scenario
from phalanx.core.states import State
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
    stood = _stood_before_reversing(log)
    return log, {
        "shape": shape, "robots": robots, "backward_s": seconds, "worst": worst,
        "stood_s": stood, **nav,
    }  # fmt: skip


def _stood_before_reversing(log: RunLog) -> list[float]:
    """For each deadlock reverse, the seconds from the deadlock (the leader entering
    DEADLOCK_REVERSE) to its first step backwards: the turn back and the pause.
    """
    backing = np.flatnonzero(leader_direction(log) < 0)
    entered = sorted(
        e.t_s for events in log.transitions.values() for e in events
        if e.target == State.DEADLOCK_REVERSE
    )  # fmt: skip
    stood = []
    for t_s in entered:
        after = backing[log.t_s[backing] >= t_s]
        if after.size:
            stood.append(float(log.t_s[after[0]]) - t_s)
    return stood


def _fmt(value: float, digits: int = 3) -> str:
    return "n/a" if not math.isfinite(value) else f"{value:.{digits}g}"


def field_table(summaries: dict[tuple[str, int], dict[str, Any]]) -> list[str]:
    """Markdown: one row per shape and group size (printed; the sweep's table in
    docs/RESULTS.md holds the same runs).
    """
    rows = [
        "| formation | robots | runs | goal reached | stuck | collisions robot-obstacle / "
        "robot-robot | deadlock reverses (runs) | leadership changes | time to goal mean / "
        "median / max | calm linear % mean / max | calm angular % mean / max | calm "
        "orientation deg mean / max | calm linear m mean / max | time in episodes |",
        "|---|---:|---:|---:|---:|---|---|---:|---|---|---|---|---|---:|",
    ]
    for (shape, robots), s in summaries.items():
        c = s["calm"]
        rows.append(
            f"| {shape} | {robots} | {s['runs']} | {100 * s['reached'] / s['runs']:.0f} % "
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
    """Markdown: the dead end per shape and group size, the backward phase against the
    core bounds (a dash where no reverse was measured).
    """
    rows = [
        "| formation | robots | deadlock reverses | measured reverse | backward linear max % "
        "| backward angular max % | backward orientation max deg | deadlock to reverse "
        "| goal reached | collisions |",
        "|---|---:|---:|---:|---|---|---|---:|---|---:|",
    ]
    for r in results:
        w = r["worst"]
        measured = r["backward_s"] > 0
        errors = [
            f"{_fmt(w[k])} {'✗' if w[k] > bound else '✓'}" if measured else "-"
            for k, bound in CORE_BOUNDS.items()
        ]
        cells = [
            r["shape"], str(r["robots"]), str(r["deadlock_reverses"]), _reverse(r), *errors,
            " / ".join(f"{s:.1f} s" for s in r["stood_s"]) or "-",
            f"yes ({r['time_to_goal_s']:.0f} s)" if r["goal_reached"] else "no",
            str(r["collisions_obstacle"] + r["collisions_robot"]),
        ]  # fmt: skip
        rows.append("| " + " | ".join(cells) + " |")
    return rows


def _reverse(result: dict[str, Any]) -> str:
    """How long the measured reverse lasted, or why there was none."""
    if result["backward_s"] > 0:
        return f"{result['backward_s']:.3g} s"
    return "none (no dead end called)" if not result["deadlock_reverses"] else "none measured"


# The figures of the section: (file under docs/figures, the group it draws, its caption).
DEADEND_FIGURES = (
    (
        "deadend-inline3-escape.png",
        ("inline", 3),
        "dead end, chain of three: round the U, never in",
    ),
    ("deadend-wedge3-escape.png", ("wedge", 3), "dead end, wedge"),
)


def section(deadends: list[dict[str, Any]]) -> str:
    """The navigation part of docs/RESULTS.md: what the seeded fields are (the sweep's
    section after it holds their table), the dead end, its table, notes and figures.
    """
    lines = [
        SECTION_BEGIN,
        "## Navigation: seeded obstacle fields and the dead end",
        "",
        "### The seeded obstacle fields",
        "",
        FIELDS_TEXT,
        "",
        "### The U-shaped dead end, escaped in reverse",
        "",
        DEADEND_TEXT,
        "",
        MEASURED_TEXT,
        "",
        *deadend_table(deadends),
        "",
        DEADEND_NOTES,
        "",
        *(f"![{caption}](figures/{name})\n" for name, _, caption in DEADEND_FIGURES),
        SECTION_END,
    ]
    return "\n".join(lines)


FIELDS_TEXT = (
    'Each run: `navigation_scenario("field", shape, robots, seed=s)` (the scenario of '
    "`configs/scenarios/nav_field_*.toml` with field seed s): 18 round obstacles "
    "(0.2-0.45 m, at least 1.2 m apart) scattered between start and goal 24 m away in a "
    "12 m wide arena, the leader navigating on sonar alone (reactive steering over a "
    "map it builds), followers in formation with `ours`, |v| <= 0.3 m/s, |omega| <= 40 "
    "deg/s, at most 240 s. Collisions count contact episodes (ground truth). *Calm* "
    "errors are the paper's formation errors (against the robot each follower tracks, "
    "all followers' steps pooled) outside obstacle-avoidance episodes: an episode runs "
    "from a robot leaving its slot (AVOID, EMERGENCY_STOP, HOLD, JOIN, STUCK) until it "
    "is back in it (within 0.1 m, or a tenth of its slot's distance from the leader if "
    "more, and 15 deg), or while the leader turns the shape on the spot or away from a "
    "dead end (DEADLOCK_TURN), and `settle_s` = 5 s after; the deadlock reverse itself "
    "is measured. A run that does not reach the goal ran out of its 240 s or ended "
    "STUCK (deadlock retries used up). The sweep below runs 100 of these fields for "
    "every formation of three and of five robots."
)
DEADEND_TEXT = (
    "`configs/scenarios/nav_deadend_*.toml`: a U 1.2 m wider than the shape, 8 m deep "
    "(its end out of sonar range from the mouth), the goal behind it. The group drives "
    "in; once the leader's map shows its route leading back the way it came (the point "
    "it heads for behind it and within 1 m of the path it drove) and no room to turn "
    "the shape round, the group is in deadlock: it turns the shape back to the way it "
    "came in (the heading of the leader's last 2 m of path: a leader caught turning "
    "would otherwise back out diagonally), stands still until every follower says it "
    "has settled onto its slot, position then heading (at most 12 s, "
    "`deadlock.pause_s`; `pause_until_settled`), backs out straight in formation "
    "(`deadlock.reverse_mode = 'fixed'`, as the paper) for 10 m, turns towards the "
    "route and goes round. Backward-phase errors are measured from 5 s after the "
    "reverse starts (the formation-core convention), against the formation-core bounds "
    "(< 0.5 % linear, < 0.3 % angular, < 0.5 deg orientation)."
)
MEASURED_TEXT = (
    "Measured with `bench_montecarlo.deadend_run(shape, robots)` of "
    "`bench/bench_montecarlo.py` on each `configs/scenarios/nav_deadend_*.toml`, run to "
    "its end (`phalanx run configs/scenarios/nav_deadend_wedge5.toml` runs one with its "
    "figures):"
)
# What the table shows, written by hand: read it again when the numbers change.
DEADEND_NOTES = """\
- **Every reverse stays within the bounds.** The wedge and the line abreast fold into a
  column on the way in; a column's followers keep to the path driven ahead of them
  (`[navigation] column_path`), so they do not swing into the U's walls on its bends.
  While the leader stands before the reverse, each follower settles onto its slot to
  within 5 mm (it turns towards the slot, drives onto it, then turns on the spot to the
  slot's heading: `Track`, `phalanx.agents.behaviours.follower`), which is what keeps the
  reverse within the bounds from its fifth second on. Each says so once within 0.5 deg
  of the heading, and the leader backs off once all have: 15.4 and 13.2 s after the
  deadlock, the turn back included, against 17.3 and 16.3 s standing the whole 12 s
  (`--set deadlock.pause_until_settled=false`).
- **The chains go round, never in.** At the U's mouth the sonar's arcs close and open the
  mouth on the leader's map from one re-plan to the next, so its route flips between going
  in and going round; a dead end is called only when the route has led back for 2 s
  running (`DEAD_END_CONFIRM_S`, `phalanx.agents.sensing`). A chain's leader turns as
  fast as its second robot's slot allows (the robots behind it trail), so it turns towards
  the way round while that is offered and keeps to it.
- **A column turned round inside the U.** The wedge and the line abreast of five fold
  into a column, which turns round inside the U (its followers keep to the path) and
  drives out along the U's wall; at the mouth its route turns back round the wall's end,
  behind the leader but not the way it came, and the group drives on round: at the goal
  after 237 s (wedge) and 244 s (line abreast), neither calling a dead end (one is a
  route leading back along the path driven: the point the leader heads for within 1 m
  of it, but for its last 2 m). The U's 0.3 m walls stay on the leader's map while the
  robots drive along them: a sonar beam that meets one of the formation's robots sees
  nothing behind it, and a guess at a beam's edge weighs a third of an echo on its axis
  ([NAVIGATION.md](NAVIGATION.md), "What a scan adds to the map")."""


def main() -> None:
    Calibration.measure()  # (the unit every time below can be divided by, on any machine)
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=0, help="seeded fields per shape (printed)")
    parser.add_argument("--robots", type=int, nargs="+", default=[3, 5])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--shapes", nargs="+", default=list(SHAPES))
    parser.add_argument("--write", action="store_true", help="rewrite docs/RESULTS.md's part")
    args = parser.parse_args()
    groups = [(shape, robots) for robots in args.robots for shape in args.shapes]
    jobs = [(shape, robots, seed) for shape, robots in groups for seed in range(args.seeds)]
    started = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        rows = list(pool.map(field_run, jobs, chunksize=2))
        deadends_out = list(pool.map(deadend_run, *zip(*groups, strict=True)))
    deadends = [d for _, d in deadends_out]
    print(
        f"{len(jobs)} field runs, {len(groups)} dead ends in {time.perf_counter() - started:.0f} s"
    )
    if rows:
        summaries = {
            g: summarise([r for r in rows if (r["shape"], r["robots"]) == g]) for g in groups
        }
        print("\n".join(field_table(summaries)))
        for shape, robots in groups:
            failed = [
                r["seed"]
                for r in rows
                if (r["shape"], r["robots"]) == (shape, robots) and not r["goal_reached"]
            ]
            print(f"{shape} {robots}: seeds not reaching the goal: {failed}")
        print()
    print("\n".join(deadend_table(deadends)))
    if args.write:
        write_docs(deadends_out)


def write_docs(deadends_out: list[tuple[RunLog, dict[str, Any]]]) -> None:
    """Rewrite the navigation part of docs/RESULTS.md and its figures."""
    from phalanx.analysis.figures import deadend_escape, save_figure, states

    figures = REPO / "docs" / "figures"
    logs = {(d["shape"], d["robots"]): log for log, d in deadends_out}
    for name, group, _ in DEADEND_FIGURES:
        if group in logs:
            save_figure(deadend_escape(logs[group]), figures / name)
    if ("wedge", 3) in logs:
        save_figure(states(logs["wedge", 3]), figures / "deadend-wedge3-fig4b_states.png")
    path = REPO / "docs" / "RESULTS.md"
    text = section([d for _, d in deadends_out])
    path.write_text(with_section(path.read_text(encoding="utf-8"), text), encoding="utf-8")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
