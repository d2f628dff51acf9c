"""What a world process writes down of the robots' own states: an agent late on a loaded
machine skips ticks (its clock does not bunch them up), and the pose it published ticks
before is not its estimate at the ticks it skipped: the estimation errors are measured
at the ticks it published for, while its behaviour state and twist are held over."""

from __future__ import annotations

import numpy as np
import pytest

from phalanx.analysis.estimation import robot_estimation
from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_robot, load_scenario
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.runtime.run_record import RunRecord
from phalanx.simulator.world import World
from phalanx.wire.messages import RobotState

SPEED_MPS = 0.15
SKIPPED = (40, 41, 42, 59)  # ticks the agent was too late for (three in a row, the last)


def _state(k: int, dt_s: float) -> RobotState:
    return RobotState(
        robot_id="r1", seq=k + 1, stamp_s=k * dt_s, x_m=SPEED_MPS * k * dt_s, y_m=0.0,
        theta_rad=0.0, v_mps=SPEED_MPS, omega_radps=0.0, fsm_state="FORMATION_TRACK",
        cov=(1e-6, 0.0, 0.0, 1e-6, 0.0, 1e-6),
    )  # fmt: skip


def test_a_robot_that_skipped_ticks_is_measured_where_it_published() -> None:
    scenario = apply_overrides(
        load_scenario(CONFIG_ROOT / "scenarios" / "real_wedge.toml"),
        ["duration_s=6", "initial_settle_s=0"],
    )
    robot = load_robot("p3dx")
    world = World.for_scenario(scenario, robot)
    record = RunRecord(scenario, scenario_formation(scenario), ("r1",))
    dt_s = scenario.dt_s
    for k in range(record.steps):  # the robot where its states say, exactly
        world.place("r1", Pose2D(SPEED_MPS * k * dt_s, 0.0, 0.0), Twist2D(SPEED_MPS, 0.0))
        record.record(k, world, {"r1": Twist2D(SPEED_MPS, 0.0)}, None)
    states = {k: _state(k, dt_s) for k in range(record.steps) if k not in SKIPPED}
    log = record.log(
        robot, states={"r1": states}, events=(), reports={}, observed=None, world=world,
        runtime={}, wall_time_s=6.0,
    )  # fmt: skip
    trace = log.traces["r1"]
    assert np.isnan(trace.estimate[list(SKIPPED)]).all()
    assert np.isnan(trace.cov[list(SKIPPED)]).all()
    assert np.isfinite(trace.estimate[[k for k in range(record.steps) if k not in SKIPPED]]).all()
    assert trace.states[SKIPPED[-1]] == "FORMATION_TRACK"  # behaviour held over
    errors = robot_estimation(log, "r1")
    assert errors["position_m"]["max"] == pytest.approx(0.0, abs=1e-9)
    assert errors["nees_steps"] == record.steps - len(SKIPPED)
    assert errors["final_position_m"] == pytest.approx(0.0, abs=1e-9)
