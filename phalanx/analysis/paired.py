"""Two sweeps of the same fields compared run by run (`phalanx sweep-compare`).

A change to the navigation moves some runs of a row one way and some the other: in the
seeded fields a small difference early on grows into another route. A row's share of
goals reached alone cannot tell a change that helps from one that only reshuffles which
runs succeed. Pairing the runs of two results files by field (family, formation, group
size, controller, seed) can: the runs one sweep reached and the other did not are what
changed, and an exact sign test on them (two-sided) says how likely so lopsided a split
is by chance. Each row's reach also gets its Wilson 95 % interval.

Results files are JSON lines as `phalanx sweep` writes them; they are checked like any
file from a user: a line that is not a sweep run's record (`SweepRow`) is skipped and
counted, and a field that two runs of one file claim (two sweeps with different `--set`s
in one file) is an error, not a guess.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from phalanx.analysis.sweep_row import SweepRow
from phalanx.core.errors import ConfigError

Group = tuple[str, str, int, str]  # (family, formation, robots, controller)
Field = tuple[Group, int]  # a group's field: its seed
WILSON_Z = 1.959963984540054  # the 97.5 % point of the standard normal: 95 % two-sided


@dataclass(frozen=True)
class Run:
    """What the comparison reads of one run of a sweep."""

    reached: bool
    time_ratio: float | None  # time to the goal over the route's at cruise (None: missed)
    reverses: int
    episode_share: float


@dataclass(frozen=True)
class Sweep:
    """A results file's runs by field, and how many of its lines were not runs."""

    runs: dict[Field, Run]
    skipped: int


@dataclass(frozen=True)
class Paired:
    """One group's runs in both sweeps, compared field by field."""

    group: Group
    runs: int
    reached: tuple[int, int]  # (before, after)
    gained: tuple[int, ...]  # seeds reached after only
    lost: tuple[int, ...]  # seeds reached before only
    p_value: float  # exact two-sided sign test on gained against lost
    reverses: tuple[int, int]
    episode_share: tuple[float, float]  # mean over the runs
    time_ratio: tuple[float, float]  # median over the runs both reached

    @property
    def intervals(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """The Wilson 95 % interval of each sweep's share of goals reached."""
        return wilson(self.reached[0], self.runs), wilson(self.reached[1], self.runs)


def sign_test_p(gained: int, lost: int) -> float:
    """Two-sided exact sign test: the chance of a split at least this lopsided between
    `gained` and `lost` runs if either way were equally likely (1.0 with none).
    """
    if gained < 0 or lost < 0:
        raise ValueError("run counts cannot be negative")
    n = gained + lost
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(min(gained, lost) + 1))
    return min(1.0, 2.0 * tail / 2.0**n)


def wilson(successes: int, trials: int, z: float = WILSON_Z) -> tuple[float, float]:
    """The Wilson score interval of a share `successes / trials` ((0, 1) with no trials)."""
    if not 0 <= successes <= trials:
        raise ValueError(f"{successes} successes out of {trials} trials")
    if trials == 0:
        return 0.0, 1.0
    p = successes / trials
    z2 = z * z
    centre = (p + z2 / (2 * trials)) / (1 + z2 / trials)
    half = z / (1 + z2 / trials) * math.sqrt(p * (1 - p) / trials + z2 / (4 * trials * trials))
    # (at a share of 0 or 1 the interval ends there exactly, not a rounding short of it)
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == trials else min(1.0, centre + half)
    return low, high


def _run_of(row: dict[str, Any]) -> tuple[Field, Run] | None:
    """A sweep run's record (`SweepRow`'s) as its field and run; None for one whose
    share of time in avoidance episodes is not known (a run of no step).
    """
    job, share = row["job"], row["episode_share"]
    if math.isnan(share):
        return None
    time, route = row["time_to_goal_s"], row["route_s"]
    known = row["goal_reached"] and time is not None and math.isfinite(route) and route > 0
    group = (job["course"], job["shape"], job["robots"], job["controller"])
    run = Run(row["goal_reached"], time / route if known else None, row["deadlock_reverses"], share)
    return (group, job["seed"]), run


def load_sweep(path: Path) -> Sweep:
    """The runs of a `phalanx sweep` results file, by field."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the results file: {exc}") from exc
    runs: dict[Field, Run] = {}
    skipped = 0
    for number, line in enumerate(lines, start=1):
        row = SweepRow.of(line)
        parsed = None if row is None else _run_of(row)
        if parsed is None:
            skipped += 1
            continue
        field, run = parsed
        if field in runs:
            (course, shape, robots, controller), seed = field
            raise ConfigError(
                f"{path}:{number}: a second run of {course}/{shape}{robots}/{controller} "
                f"seed {seed} (two sweeps in one file, with different --set?): compare "
                "files that hold one sweep each"
            )
        runs[field] = run
    return Sweep(runs, skipped)


def _median(values: list[float]) -> float:
    return statistics.median(values) if values else math.nan


def compare(before: Sweep, after: Sweep) -> list[Paired]:
    """Every group both sweeps ran, over the fields both ran, in `before`'s order."""
    common = [f for f in before.runs if f in after.runs]
    groups: dict[Group, list[int]] = {}
    for group, seed in common:
        groups.setdefault(group, []).append(seed)
    out = []
    for group, seeds in groups.items():
        pairs = [(before.runs[(group, s)], after.runs[(group, s)]) for s in seeds]
        gained = tuple(s for s, (b, a) in zip(seeds, pairs, strict=True) if a.reached > b.reached)
        lost = tuple(s for s, (b, a) in zip(seeds, pairs, strict=True) if b.reached > a.reached)
        both = [(b.time_ratio, a.time_ratio) for b, a in pairs if b.reached and a.reached]
        out.append(
            Paired(
                group=group,
                runs=len(seeds),
                reached=(sum(b.reached for b, _ in pairs), sum(a.reached for _, a in pairs)),
                gained=gained,
                lost=lost,
                p_value=sign_test_p(len(gained), len(lost)),
                reverses=(sum(b.reverses for b, _ in pairs), sum(a.reverses for _, a in pairs)),
                episode_share=(
                    sum(b.episode_share for b, _ in pairs) / len(pairs),
                    sum(a.episode_share for _, a in pairs) / len(pairs),
                ),
                time_ratio=(
                    _median([b for b, _ in both if b is not None]),
                    _median([a for _, a in both if a is not None]),
                ),
            )
        )
    return out


def _seeds(seeds: tuple[int, ...]) -> str:
    return f"{len(seeds)} ({', '.join(map(str, seeds))})" if seeds else "0"


def _pct(low_high: tuple[float, float]) -> str:
    return f"{100 * low_high[0]:.0f}-{100 * low_high[1]:.0f} %"


def table(pairs: list[Paired]) -> list[str]:
    """Markdown: one row per group."""
    rows = [
        "| family | formation | robots | controller | runs in both | reached before (95 %) "
        "| reached after (95 %) | gained (seeds) | lost (seeds) | sign test p "
        "| deadlock reverses | time in episodes | median time / route (both reached) |",
        "|---|---|---:|---|---:|---|---|---|---|---:|---|---|---|",
    ]
    for p in pairs:
        (course, shape, robots, controller), (ib, ia) = p.group, p.intervals
        rows.append(
            f"| {course} | {shape} | {robots} | {controller} | {p.runs} "
            f"| {p.reached[0]} ({_pct(ib)}) | {p.reached[1]} ({_pct(ia)}) "
            f"| {_seeds(p.gained)} | {_seeds(p.lost)} | {p.p_value:.2g} "
            f"| {p.reverses[0]} -> {p.reverses[1]} "
            f"| {100 * p.episode_share[0]:.0f} -> {100 * p.episode_share[1]:.0f} % "
            f"| {p.time_ratio[0]:.3g} -> {p.time_ratio[1]:.3g} |"
        )
    return rows
