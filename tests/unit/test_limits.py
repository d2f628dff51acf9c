"""One rule for a run's speed limits, the tighter of the robot's rating and the scenario's
run bounds, used by both layers: the limiter after every controller and the safety layer
around every driver. A scenario can tighten the robot's limits, never loosen them.
"""

from __future__ import annotations

import math

import pytest

from phalanx.agents.agent import Agent
from phalanx.core.config import LimitsOverride
from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_robot, load_scenario
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import Twist2D
from phalanx.core.limits import run_limits, safety_limits
from phalanx.drivers.safety import SafeDriver
from phalanx.drivers.sim import SimDriver

ROBOT = load_robot("p3dx")
WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"


def test_a_scenario_tighter_than_the_robot_tightens_both_layers() -> None:
    override = LimitsOverride(v_max_mps=0.3, omega_max_degps=40.0)
    inner, outer = run_limits(ROBOT, override), safety_limits(ROBOT, override)
    assert (inner.v_max_mps, outer.v_max_mps) == (0.3, 0.3)
    assert inner.omega_max_radps == outer.omega_max_radps == pytest.approx(math.radians(40.0))


@pytest.mark.parametrize(("v_max_mps", "omega_max_degps"), [(5.0, 1000.0), (1.21, 300.5)])
def test_a_scenario_above_the_robots_rating_is_clamped_to_it_by_both_layers(
    v_max_mps: float, omega_max_degps: float
) -> None:
    sets = [f"limits.v_max_mps={v_max_mps}", f"limits.omega_max_degps={omega_max_degps}"]
    scenario = apply_overrides(load_scenario(WEDGE), sets)
    rated = (ROBOT.v_max_mps, ROBOT.omega_max_radps)
    # The inner layer: the agent's limiter saturates an absurd command at the rating.
    agent = Agent("r1", scenario=scenario, robot=ROBOT, formation=scenario_formation(scenario))
    assert (agent.limits.v_max_mps, agent.limits.omega_max_radps) == rated
    limiter = agent.limiter
    for _ in range(200):  # long enough for the acceleration limit to reach the bound
        command = limiter.apply(Twist2D(10.0, 0.0), scenario.dt_s)
    assert command.v_mps == pytest.approx(ROBOT.v_max_mps)
    # The outer layer: the safety wrapper around a driver clamps at the rating too.
    limits = safety_limits(ROBOT, scenario.limits, watchdog_s=0.5)
    assert (limits.v_max_mps, limits.omega_max_radps) == rated
    with SafeDriver(SimDriver(ROBOT), limits) as safe:
        sent = safe.set_velocity(Twist2D(10.0, 10.0))
    assert sent.v_mps <= ROBOT.v_max_mps + 1e-12
    assert sent.omega_radps <= ROBOT.omega_max_radps + 1e-12
    assert safe.stats.clamped == 1


def test_an_emergency_stop_brakes_at_the_robots_emergency_limits() -> None:
    from phalanx.agents.control.limits import CommandLimiter
    from phalanx.core.config_files import load_robot
    from phalanx.core.geometry import ZERO_TWIST, Twist2D
    from phalanx.core.limits import run_limits

    robot = load_robot("p3dx")
    limits = run_limits(robot)
    assert limits.emergency_decel_mps2 == robot.emergency_decel_mps2 == 2.0
    moving = Twist2D(0.3, 0.5)

    def steps_to_zero(emergency: bool) -> int:
        limiter = CommandLimiter(limits)
        limiter.reset(moving)
        for step in range(1, 100):
            if limiter.apply(ZERO_TWIST, 0.1, emergency=emergency) == ZERO_TWIST:
                return step
        return 100

    assert steps_to_zero(emergency=False) >= 10  # 0.3 m/s at the comfortable 0.3 m/s^2
    assert steps_to_zero(emergency=True) == 2  # ... at 2 m/s^2 (and 300 deg/s^2)
    # Emergency limits only ever brake: speeding up, or to a twist other than zero, is
    # rate-limited as always.
    limiter = CommandLimiter(limits)
    assert limiter.apply(Twist2D(0.3, 0.0), 0.1, emergency=True).v_mps == 0.03
