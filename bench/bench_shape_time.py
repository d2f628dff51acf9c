"""How long the way stays wide enough for the scenario's shape in the seeded fields, and
the most of that time any rule of when to reshape could keep the group in its shape.

Runs `Job("field", shape, robots, seed)` as `phalanx sweep` does, for every seed of the
range, and prints: the stretches the leader's map showed the scenario's shape fitting
(how many, their length's quartiles), the share of the fitting time the group was in
the shape (and of that, with no robot off its slot going round an obstacle or settling
after it: `phalanx.analysis.metrics.episode_mask`; and with every step of a slide back
into the shape counted as fitting, where the map the leader gauges the way on shows the
sliding robots as obstacles), and the bound
`phalanx.analysis.shape_time.kept_at_most` gives that share
for a group back in the shape `U` s after a narrowing that rides through those shorter
than `G` s (on the way these runs took).

    .venv/bin/python bench/bench_shape_time.py [--shape wedge collateral] [--robots 3]
        [--seeds 10 30] [--workers 2]
"""

from __future__ import annotations

import argparse
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from phalanx.analysis.metrics import episode_mask, leader_shape_keys, scenario_shape_series
from phalanx.analysis.shape_time import kept_at_most, returns_s, stretches
from phalanx.analysis.sweep import Job, run_until_done
from phalanx.core.runlog import RunLog
from phalanx.core.shapes import SCENARIO_SHAPE
from phalanx.runtime.batch import BatchRunner

BACK_S = (0.0, 2.0, 3.0, 5.0, 8.0)
RIDE_S = (0.0, 2.0, 4.0, 8.0)

Series = tuple[np.ndarray, np.ndarray, float]


def series(job: Job) -> tuple[Series, np.ndarray, np.ndarray]:
    """One run's in-shape and fitting series (the leader's view) and its step (s); per
    step, whether no robot was in an avoidance episode, and whether the group was sliding
    back into the scenario's shape.
    """
    log = run_until_done(BatchRunner(job.scenario()))
    got = scenario_shape_series(log)
    if got is None:
        raise SystemExit(f"{job.key}: the run recorded no shape or fitting series")
    calm = ~episode_mask(log, reshaping=False)
    return (got[0], got[1], log.scenario.dt_s), calm, _unfolding(log)


def _unfolding(log: RunLog) -> np.ndarray:
    """Per step, whether the group (as its leader then saw it) slid back into the
    scenario's shape.
    """
    keys = leader_shape_keys(log)
    return np.array([k.target == SCENARIO_SHAPE and not k.settled for k in keys], dtype=bool)


def report(
    label: str, runs: list[Series], calm: list[np.ndarray], unfolding: list[np.ndarray]
) -> None:
    """The stretches, the share kept (kept calm; with every unfolding step counted as
    fitting) and the bounds, pooled over the runs.
    """
    dt_s = runs[0][2]
    lengths_s = np.array([(b - a) * dt_s for _, fits, _ in runs for a, b in stretches(fits)])
    fitting = sum(int(fits.sum()) for _, fits, _ in runs)
    kept = sum(int((shape & fits).sum()) for shape, fits, _ in runs)
    whole = sum(
        int((shape & fits & c).sum()) for (shape, fits, _), c in zip(runs, calm, strict=True)
    )
    if not fitting:
        print(f"{label}: the shape never fitted")
        return
    widened = [fits | u for (_, fits, _), u in zip(runs, unfolding, strict=True)]
    kept_wide = sum(int((shape & w).sum()) for (shape, _, _), w in zip(runs, widened, strict=True))
    share_wide = kept_wide / sum(int(w.sum()) for w in widened)
    q1, q2, q3 = np.percentile(lengths_s, (25, 50, 75))
    print(
        f"{label}: {lengths_s.size} stretches, {fitting * dt_s:.0f} s fitting; "
        f"length quartiles {q1:.1f} / {q2:.1f} / {q3:.1f} s, mean {lengths_s.mean():.1f} s; "
        f"in the shape {kept / fitting:.0%} of it, every robot on its slot {whole / fitting:.0%};"
        f" in the shape {share_wide:.0%} with every step of an unfold counted as fitting"
    )
    back_s, never = [], 0
    for shape, fits, dt in runs:
        got, missed = returns_s(shape, fits, dt)
        back_s += got
        never += missed
    if back_s:
        print(
            f"  out of the shape when the way widened: back in it after {np.median(back_s):.1f} s"
            f" (median of {len(back_s)}), never in {never} more stretches"
        )
    print("  at most, back in the shape U s after a narrowing, riding through those under G s")
    print("  " + " " * 8 + "".join(f"  U = {u:>3.0f} s" for u in BACK_S))
    for ride_s in RIDE_S:
        bounds = [
            sum(kept_at_most(f, dt, back_s=u, ride_s=ride_s) for _, f, dt in runs) / fitting
            for u in BACK_S
        ]
        print(f"  G = {ride_s:>3.0f} s" + "".join(f"  {b:>9.0%}" for b in bounds))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shape", nargs="+", default=["wedge", "collateral"])
    parser.add_argument("--robots", nargs="+", type=int, default=[3])
    parser.add_argument("--seeds", nargs=2, type=int, default=[10, 30], metavar=("FIRST", "END"))
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    with ProcessPoolExecutor(args.workers) as pool:
        for shape in args.shape:
            for robots in args.robots:
                jobs = [Job("field", shape, robots, s) for s in range(*args.seeds)]
                runs, calm, unfolding = zip(*pool.map(series, jobs), strict=True)
                first, end = args.seeds
                label = f"{shape} of {robots}, seeds {first}-{end - 1}"
                report(label, list(runs), list(calm), list(unfolding))


if __name__ == "__main__":
    main()
