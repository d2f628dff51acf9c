"""`phalanx sweep`: many navigation runs (a scenario family x seeds x controllers x
formations x group sizes) on Dask's distributed scheduler, on this machine's worker
processes by default or on a cluster given its scheduler's address.

Why Dask (distributed) rather than Ray: a sweep is a bag of independent, CPU-bound,
pure-Python runs of a few seconds each, which is exactly a `Client.map` over worker
processes; Dask's scheduler and workers are plain Python packages (no separate
object-store or raylet daemons), a `LocalCluster` of two worker processes starts in a
second or two on a two-core machine (what CI has), and a cluster is one
`dask scheduler` plus any number of `dask worker ADDRESS` processes on machines that
have phalanx installed. Ray would bring a larger runtime per node for no feature a
sweep uses.

Every finished run is appended to a JSON-lines file as soon as it comes back, so a
sweep that is stopped and started again runs only what is missing (resumable); the
rows are gathered into one table per (family, formation, robots, controller).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from phalanx.agents.navigation.grid import MAX_EVIDENCE, OccupancyMap
from phalanx.analysis.metrics import navigation_metrics
from phalanx.analysis.report import SWEEP_BEGIN, SWEEP_END
from phalanx.analysis.sweep_row import SweepRow
from phalanx.core.config import Scenario
from phalanx.core.errors import ConfigError
from phalanx.core.geometry import Vec2
from phalanx.core.runlog import RunLog
from phalanx.core.scenarios import Course, Shape, navigation_scenario, resolve_world
from phalanx.runtime.batch import BatchRunner

SETTLE_AFTER_END_S = 10.0
CALM_KEYS = ("linear_pct", "angular_pct", "orientation_deg", "linear_m", "angular_deg")


@dataclass(frozen=True, slots=True)
class Job:
    """One run of a sweep: `navigation_scenario(course, shape, robots, seed=seed)` with
    `controller`, and any dotted `overrides` of the scenario (as `--set` takes them).
    """

    course: str
    shape: str
    robots: int
    seed: int
    controller: str = "ours"
    overrides: tuple[tuple[str, Any], ...] = ()

    @property
    def key(self) -> str:
        """A name unique within a sweep (what a resumed sweep skips by)."""
        extra = ",".join(f"{k}={v}" for k, v in self.overrides)
        return f"{self.course}/{self.shape}{self.robots}/{self.controller}/s{self.seed}/{extra}"

    def scenario(self) -> Scenario:
        """The run's scenario."""
        overrides = {"controller.kind": self.controller, **dict(self.overrides)}
        return navigation_scenario(
            _course(self.course), _shape(self.shape), self.robots, seed=self.seed,
            overrides=overrides,
        )  # fmt: skip


def _course(name: str) -> Course:
    if name not in ("corridor", "deadend", "field", "narrow"):
        raise ValueError(f"unknown scenario family {name!r}")
    return name  # type: ignore[return-value]


def _shape(name: str) -> Shape:
    if name not in ("wedge", "inline", "collateral"):
        raise ValueError(f"unknown formation {name!r}")
    return name  # type: ignore[return-value]


def jobs(
    courses: Iterable[str],
    shapes: Iterable[str],
    robots: Iterable[int],
    seeds: Iterable[int],
    controllers: Iterable[str] = ("ours",),
    overrides: Sequence[tuple[str, Any]] = (),
) -> list[Job]:
    """Every combination, in a fixed order."""
    return [
        Job(c, s, n, seed, k, tuple(overrides))
        for c in courses
        for s in shapes
        for n in robots
        for k in controllers
        for seed in seeds
    ]


def run_until_done(runner: BatchRunner) -> RunLog:
    """Run until a robot is ARRIVED or STUCK, then `SETTLE_AFTER_END_S` more (or to the
    scenario's end).
    """
    finished: dict[str, int] = {}
    extra = round(SETTLE_AFTER_END_S / runner.scenario.dt_s)

    def done(b: BatchRunner) -> bool:
        if "k" not in finished and any(
            a.state_name in ("ARRIVED", "STUCK") for a in b.agents.values()
        ):
            finished["k"] = b.done
        return "k" in finished and b.done - finished["k"] >= extra

    return runner.run(until=done)


def run_job(job: Job) -> dict[str, Any]:
    """One run (on whichever worker gets it): its navigation metrics and wall time."""
    started = time.perf_counter()
    log = run_until_done(BatchRunner(job.scenario()))
    return job_row(job, log, time.perf_counter() - started)


def job_row(job: Job, log: RunLog, wall_s: float) -> dict[str, Any]:
    """The results file's row of `job`, run as `log` in `wall_s` of wall time."""
    nav = navigation_metrics(log)
    row = {"job": asdict(job), "key": job.key, "wall_s": wall_s, "route_s": route_s(log), **nav}
    return SweepRow.read(json.dumps(row, allow_nan=True))  # (as a resumed sweep reads it)


def route_s(log: RunLog) -> float:
    """How long the shortest route from the leader's start to the last waypoint round
    the world's obstacles (grown by a robot's radius, on the map's 0.5 m grid) takes at
    cruise speed (s); the straight line's if there is none.
    """
    scenario = log.scenario
    start, goal = log.traces[log.formation.root].pose(0).position, scenario.navigation.waypoints
    if not goal:
        return math.nan
    end = Vec2(*goal[-1])
    grid = OccupancyMap(start)
    centres = (np.arange(grid.cells) + 0.5) * grid.cell_m
    x, y = np.meshgrid(grid.x0_m + centres, grid.y0_m + centres)  # (row = y, col = x)
    blocked = np.zeros(x.shape, dtype=bool)
    reach = log.robot.radius_m + grid.cell_m / 2
    world = resolve_world(scenario.world)
    for c in world.circles:
        blocked |= np.hypot(x - c.x_m, y - c.y_m) < c.radius_m + reach
    for p in world.polygons:  # (their bounding boxes: the courses' walls are boxes)
        xs, ys = [v[0] for v in p.vertices_m], [v[1] for v in p.vertices_m]
        blocked |= (
            (x > min(xs) - reach)
            & (x < max(xs) + reach)
            & (y > min(ys) - reach)
            & (y < max(ys) + reach)
        )
    grid.evidence[blocked] = MAX_EVIDENCE
    planned = grid.plan(start, end, keep_off_m=0.0, ahead_m=0.0)
    length_m = planned[1] if planned is not None else (end - start).norm()
    return length_m / scenario.navigation.cruise_mps


# --- the engine -------------------------------------------------------------------------


def read_rows(path: Path) -> tuple[dict[str, dict[str, Any]], int]:
    """The runs a results file already holds, by job key, and how many of its lines hold
    none (`SweepRow.of`: a torn last line, one edited, one from another version); those
    runs are done again. ConfigError if it cannot be read as text.
    """
    rows: dict[str, dict[str, Any]] = {}
    skipped = 0
    try:
        lines = path.read_text(encoding="utf-8").splitlines() if path.exists() else []
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the results file: {exc}") from exc
    for line in lines:
        row = SweepRow.of(line)
        if row is None:
            skipped += 1
        else:
            rows[row["key"]] = row
    return rows, skipped


def done_rows(path: Path) -> dict[str, dict[str, Any]]:
    """The runs a results file already holds, by job key (`read_rows`)."""
    return read_rows(path)[0]


def run_sweep(
    todo: Sequence[Job],
    results: Path,
    *,
    address: str | None = None,
    workers: int = 2,
    progress: Callable[[int, int], None] | None = None,
) -> list[dict[str, Any]]:
    """Run the jobs not in `results` yet (a JSON-lines file, appended to as runs finish)
    on a local cluster of `workers` processes, or on the cluster at `address`; every
    job's row, in the order of `todo`.
    """
    have = done_rows(results)
    pending = [j for j in todo if j.key not in have]
    total, finished = len(todo), len(todo) - len(pending)
    if progress is not None:
        progress(finished, total)
    results.parent.mkdir(parents=True, exist_ok=True)
    if pending:
        from dask.distributed import Client, as_completed

        cluster = None if address is not None else local_cluster(workers)
        try:
            client = Client(address or cluster)  # type: ignore[no-untyped-call]
            with client, results.open("a", encoding="utf-8") as out:
                # (no list of the futures kept: a run's result, once in the file, is
                # released, or the worker holding it keeps it to the end, and losing
                # that worker would have every run it ever finished done again)
                futures = as_completed(client.map(run_job, pending, pure=False))  # type: ignore[no-untyped-call]
                for future in futures:
                    row = future.result()
                    out.write(json.dumps(row, allow_nan=True) + "\n")
                    out.flush()
                    future.release()
                    have[row["key"]] = row
                    finished += 1
                    if progress is not None:
                        progress(finished, total)
        finally:
            if cluster is not None:
                cluster.close()
    return [have[j.key] for j in todo]


# Dask's housekeeping, made rarer for a sweep's own cluster. Each of these wakes a
# worker's event loop in the middle of a run, and every wake-up takes the interpreter
# lock from the run's thread: the check that the event loop is not blocked (every 20 ms
# by default), the statistical profiler's stack sample (every 10 ms), the system and
# memory monitors (every 0.5 s and 0.1 s). The scheduler and the nannies, in the
# process that runs `phalanx sweep`, tick as often, on the same two cores as the runs.
QUIET_DASK: Mapping[str, Any] = {
    "distributed.admin.tick.interval": "1s",
    "distributed.worker.profile.enabled": False,
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.memory.monitor-interval": "1s",
}


def local_cluster(workers: int, housekeeping: Mapping[str, Any] = QUIET_DASK) -> Any:
    """A `LocalCluster` of `workers` processes, one thread each, that keep glibc's own
    threshold for handing freed memory back to the system, with Dask's `housekeeping`
    settings (`QUIET_DASK`: made rarer; `{}`: Dask's own). Dask's nanny starts its
    workers with `MALLOC_TRIM_THRESHOLD_=65536`: a run's numpy temporaries then fault
    their pages in afresh step after step (25 times the page faults of the same runs in
    one process, and a tenth more time); Dask's own housekeeping costs the runs about
    6 % more time (docs/PERFORMANCE.md).
    """
    import dask
    from dask.distributed import LocalCluster

    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ"))
    environ.pop("MALLOC_TRIM_THRESHOLD_", None)
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ, **housekeeping}):
        return LocalCluster(  # type: ignore[no-untyped-call]
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None
        )


# --- the table --------------------------------------------------------------------------


def summarise(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Aggregate runs of one group (goal, collisions, times, calm errors, episodes)."""
    n = len(rows)
    reached = [r for r in rows if r["goal_reached"]]
    times = np.array([r["time_to_goal_s"] for r in reached], dtype=float)
    ratio = np.array([r["time_to_goal_s"] / r["route_s"] for r in reached if r.get("route_s")])
    calm: dict[str, dict[str, float]] = {}
    samples = sum(r["calm"]["samples"] for r in rows)
    for key in CALM_KEYS:
        weighted = [
            r["calm"][key]["mean"] * r["calm"]["samples"]
            for r in rows
            if r["calm"]["samples"] and math.isfinite(r["calm"][key]["mean"])
        ]
        maxima = [r["calm"][key]["max"] for r in rows if math.isfinite(r["calm"][key]["max"])]
        calm[key] = {
            "mean": sum(weighted) / samples if samples else math.nan,
            "max": max(maxima, default=math.nan),
        }
    return {
        "runs": n,
        "reached": len(reached),
        "stuck": sum(bool(r["stuck"]) for r in rows),
        "obstacle_collisions": sum(r["collisions_obstacle"] for r in rows),
        "robot_collisions": sum(r["collisions_robot"] for r in rows),
        "deadlock_reverses": sum(r["deadlock_reverses"] for r in rows),
        "runs_with_reverse": sum(1 for r in rows if r["deadlock_reverses"]),
        "reshapes": sum(r.get("reshapes", 0) for r in rows),
        "leadership_changes": sum(r["leadership_changes"] for r in rows),
        "episode_share": float(np.mean([r["episode_share"] for r in rows])) if rows else math.nan,
        "reshaping_share": float(np.mean([r.get("reshaping_share", 0.0) for r in rows]))
        if rows
        else math.nan,
        "scenario_shape_share": _mean(rows, "scenario_shape_share"),
        "fits_share": _mean(rows, "fits_share"),
        "scenario_shape_when_fits": _mean(rows, "scenario_shape_when_fits"),
        "time_mean_s": float(times.mean()) if times.size else math.nan,
        "time_median_s": float(np.median(times)) if times.size else math.nan,
        "time_max_s": float(times.max()) if times.size else math.nan,
        "time_ratio_median": float(np.median(ratio)) if ratio.size else math.nan,
        "calm": calm,
        "wall_s": sum(r["wall_s"] for r in rows),
    }


def _mean(rows: Sequence[dict[str, Any]], key: str) -> float:
    """The mean of a share over `rows` (1 for rows from before it was measured)."""
    return float(np.mean([r.get(key, 1.0) for r in rows])) if rows else math.nan


def group_key(row: dict[str, Any]) -> tuple[str, str, int, str]:
    """(family, formation, robots, controller) of a row."""
    job = row["job"]
    return (job["course"], job["shape"], job["robots"], job["controller"])


def summaries(rows: Sequence[dict[str, Any]]) -> dict[tuple[str, str, int, str], dict[str, Any]]:
    """`summarise` per (family, formation, robots, controller), in the rows' order."""
    groups: dict[tuple[str, str, int, str], list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault(group_key(row), []).append(row)
    return {key: summarise(group) for key, group in groups.items()}


def _fmt(value: float, digits: int = 3) -> str:
    return "n/a" if not math.isfinite(value) else f"{value:.{digits}g}"


TABLE_HEADERS = (
    "family",
    "formation",
    "robots",
    "controller",
    "runs",
    "goal reached",
    "stuck",
    "collisions robot-obstacle / robot-robot",
    "deadlock reverses (runs)",
    "reshapes",
    "time to goal median / max",
    "median time / route at cruise",
    "calm linear % mean / max",
    "calm orientation deg mean / max",
    "time in avoidance episodes",
    "time reshaping",
    "time in the scenario's shape",
    "time it fits",
    "in the shape while it fits",
)
_ALIGN = "|---|---|---:|---|---:|---:|---:|---|---|---:|---|---:|---|---|---:|---:|---:|---:|---:|"


def table_cells(groups: dict[tuple[str, str, int, str], dict[str, Any]]) -> list[list[str]]:
    """A row of cells per group, in `TABLE_HEADERS`' order."""
    rows = []
    for (course, shape, robots, controller), s in groups.items():
        c = s["calm"]
        rows.append(
            [
                course, shape, str(robots), controller, str(s["runs"]),
                f"{100 * s['reached'] / max(1, s['runs']):.0f} %", str(s["stuck"]),
                f"{s['obstacle_collisions']} / {s['robot_collisions']}",
                f"{s['deadlock_reverses']} ({s['runs_with_reverse']})", str(s["reshapes"]),
                f"{_fmt(s['time_median_s'])} / {_fmt(s['time_max_s'])} s",
                _fmt(s["time_ratio_median"]),
                f"{_fmt(c['linear_pct']['mean'])} / {_fmt(c['linear_pct']['max'])}",
                f"{_fmt(c['orientation_deg']['mean'])} / {_fmt(c['orientation_deg']['max'])}",
                _share(s["episode_share"]), _share(s["reshaping_share"]),
                _share(s["scenario_shape_share"]), _share(s["fits_share"]),
                _share(s["scenario_shape_when_fits"]),
            ]
        )  # fmt: skip
    return rows


def _share(value: float) -> str:
    return f"{100 * value:.0f} %"


def table(groups: dict[tuple[str, str, int, str], dict[str, Any]]) -> list[str]:
    """Markdown: one row per group (what RESULTS.md's section holds)."""
    head = "| " + " | ".join(TABLE_HEADERS) + " |"
    return [head, _ALIGN, *("| " + " | ".join(row) + " |" for row in table_cells(groups))]


def terminal_table(
    groups: dict[tuple[str, str, int, str], dict[str, Any]],
    *,
    width: int,
    markdown: bool = False,
) -> list[str]:
    """The table for a terminal, fitted to `width` columns (`report.text_table`): side by
    side when its 19 columns fit, else a block of `field: value` lines per group; Markdown
    if asked.
    """
    from phalanx.analysis.report import text_table

    title = "navigation sweep: a row per family, formation, robots and controller"
    return text_table(
        TABLE_HEADERS, table_cells(groups), width=width, markdown=markdown, title=title
    )


def section(command: str, groups: dict[tuple[str, str, int, str], dict[str, Any]]) -> str:
    """The sweep's part of docs/RESULTS.md."""
    return "\n".join(
        [
            SWEEP_BEGIN,
            "## Navigation sweep (`phalanx sweep`)",
            "",
            f"Reproduce with `{command}`. Each run goes on until the goal or STUCK, "
            "plus 10 s; *median time / route at cruise*: time to "
            "the goal over the time the shortest route the map gives at the start (on the "
            "world's obstacles) takes at cruise speed; *time in avoidance episodes*: the share of "
            "steps some robot was off its slot on purpose, stopped for an obstacle or turning "
            "the shape on the spot (plus `settle_s` after each), the calm errors being taken "
            "outside these and outside reshaping; *time reshaping*: the share of steps the "
            "group slid between two shapes; *time in the scenario's shape*: the "
            "share of steps the group was in the shape the scenario asks for (not shrunk, "
            "folded or between two); *time it fits*: the share of steps the leader's map "
            "showed the way as wide as that shape (every slot's place across the heading "
            "clear, the row shifted up to 0.5 m to a side, where the group is and 1 m and "
            "2 m along the leader's route; and its footprint's route to the goal about as "
            "good as the best; looked at every second, also while the slots slide), and "
            "*in the shape while it fits*: the share of those steps the group was in it.",
            "",
            *table(groups),
            "",
            SWEEP_END,
        ]
    )
