"""Whether the scenario's shape fits the way, as the leader's map shows it, measured per
step and reported beside the time in the shape: the leader's shape keeper says so each
time it weighs the shapes (the scenario shape's footprint has a route about as good as
the best), the run records it per step (`RobotTrace.fits`), and the navigation metrics
give the share of steps it fits and the share of those the group was in the shape.
"""

from __future__ import annotations

import numpy as np
import pytest

from phalanx.agents.navigation.grid import OCCUPIED, OccupancyMap
from phalanx.agents.reshape import DECIDE_S, ShapeKeeper
from phalanx.analysis.metrics import navigation_metrics
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.formation import resolve_formation
from phalanx.core.geometry import Pose2D, Vec2
from phalanx.core.runlog import RunLog
from phalanx.core.scenarios import formation_shape
from phalanx.core.shapes import COLUMN, SCENARIO_SHAPE, ShapeBook, ShapeKey
from phalanx.runtime.batch import BatchRunner

ROBOT = load_robot("p3dx")
LINE = resolve_formation(formation_shape("collateral", 3))  # 2 m across, 0.26 m bodies
WALL_X_M = 4.0


def _walled(gap_half_m: float) -> OccupancyMap:
    """A map with a wall across the way at x = 4 m, open only within `gap_half_m` of y = 0."""
    grid = OccupancyMap(Vec2(0.0, 0.0))
    ys = np.arange(-15.0, 15.0, grid.cell_m / 2)
    ys = ys[np.abs(ys) > gap_half_m]
    row, col, _ = grid.index(np.full(ys.shape, WALL_X_M), ys)
    grid.evidence[row, col] = OCCUPIED
    return grid


@pytest.mark.parametrize(
    ("gap_half_m", "fits"),
    [(3.0, True), (0.8, False)],  # the line's footprint needs 1.41 m each side, the column's 0.41
)
def test_the_keeper_says_whether_the_scenario_shape_fits_the_way(
    gap_half_m: float, fits: bool
) -> None:
    keeper = ShapeKeeper(ShapeBook(LINE), ROBOT.radius_m)
    grid = _walled(gap_half_m)
    assert keeper.scenario_fits  # nothing weighed yet: assumed
    keeper.decide(grid, Pose2D(0.0, 0.0, 0.0), Vec2(8.0, 0.0), t_s=DECIDE_S)
    assert keeper.scenario_fits is fits
    # in the column the way fits or not just the same: it is the scenario's shape's way
    keeper.key = ShapeKey(COLUMN, COLUMN, 1.0)
    keeper.decide(grid, Pose2D(0.0, 0.0, 0.0), Vec2(8.0, 0.0), t_s=3 * DECIDE_S)
    assert keeper.scenario_fits is fits


def _narrow_run() -> RunLog:
    scenario = load_scenario(CONFIG_ROOT / "scenarios" / "nav_corridor_wedge3.toml")
    return BatchRunner(scenario.model_copy(update={"duration_s": 50.0})).run()


def test_a_run_records_per_step_whether_the_shape_fits_and_its_metrics_count_it() -> None:
    log = _narrow_run()
    n = len(log.t_s)
    assert all(len(tr.fits) == n for tr in log.traces.values())
    lead = log.traces["r1"]
    assert lead.fits[0]  # an empty map: the shape fits
    assert not all(lead.fits)  # the corridor: not all the way
    followers = [log.traces[r].fits for r in ("r2", "r3")]
    assert all(all(f) for f in followers)  # (only the leader weighs the shapes)
    # known series in place of the run's: the metrics' arithmetic, step by step
    half = n // 2
    lead.fits = [k < half for k in range(n)]
    # in the shape from the start, or back in it from the column; every fourth step
    # on the way to the column
    lead.shapes = [
        (0, COLUMN, 0.5) if k % 4 == 0
        else (SCENARIO_SHAPE, SCENARIO_SHAPE, 1.0) if k < n // 3
        else (COLUMN, SCENARIO_SHAPE, 1.0)
        for k in range(n)
    ]  # fmt: skip
    metrics = navigation_metrics(log)
    assert metrics["fits_share"] == pytest.approx(half / n)
    kept = sum(1 for k in range(half) if k % 4)
    assert metrics["scenario_shape_when_fits"] == pytest.approx(kept / half)
    assert metrics["scenario_shape_share"] == pytest.approx(sum(1 for k in range(n) if k % 4) / n)
