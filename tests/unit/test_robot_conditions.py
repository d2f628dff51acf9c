"""The robot's own conditions are states of the behaviour stack: what its driver reports
(E-stop, a fault, a stalled wheel, a low battery) stops the agent, logged with the
reason, until it clears; the battery with a little hysteresis.
"""

from __future__ import annotations

import itertools
from dataclasses import replace

from phalanx.agents.agent import Agent, Observation, StepOutput
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.core.states import State

ROBOT = load_robot("p3dx")
SCENARIO = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
FREE = RobotStatus(sonar_ranges_m=(5.0,) * 16, bumpers=(False,), battery_v=12.6)


def _run(statuses: list[RobotStatus]) -> list[StepOutput]:
    agent = Agent("r1", scenario=SCENARIO, robot=ROBOT, formation=scenario_formation(SCENARIO))
    odometry = Odometry(Pose2D(0.0, 0.0, 0.0), Twist2D(0.0, 0.0), 0.0)
    outs = []
    for k, status in enumerate(statuses):
        t_s = k * SCENARIO.dt_s
        outs.append(agent.step(Observation(replace(odometry, stamp_s=t_s), status), {}, t_s))
    return outs


def test_a_low_battery_stops_the_robot_until_it_is_well_above_the_mark() -> None:
    volts = [12.6] * 5 + [10.9] * 5 + [11.1] * 5 + [11.4] * 5
    outs = _run([replace(FREE, battery_v=v) for v in volts])
    states = [o.state.fsm_state for o in outs]
    assert states[:5] == [State.NAVIGATE] * 5
    assert states[5:15] == [State.LOW_BATTERY] * 10  # 11.1 V: above 11 V, not by 0.3 V
    assert states[15:] == [State.NAVIGATE] * 5
    event = next(e for o in outs for e in o.events if e.target == State.LOW_BATTERY)
    assert event.reason == "the battery is low: 10.9 V"


def test_an_estop_then_a_fault_each_stop_the_robot_with_their_reason() -> None:
    statuses = [FREE] * 20 + [replace(FREE, estopped=True)] * 20
    statuses += [replace(FREE, faults=("link lost: no SIP for 1.0 s",))] * 5 + [FREE] * 2
    outs = _run(statuses)
    states = [o.state.fsm_state for o in outs]
    assert states[20:40] == [State.ESTOPPED] * 20
    assert states[40:45] == [State.FAULT] * 5
    assert states[45:] == [State.NAVIGATE] * 2
    moving = outs[19].command.v_mps
    assert moving > 0.0
    speeds = [o.command.v_mps for o in outs[20:40]]  # braking within the limits to zero
    assert all(b < a for a, b in itertools.pairwise(speeds) if a > 0.0)
    assert speeds[-1] == 0.0
    reasons = [e.reason for o in outs for e in o.events]
    assert "the robot reports a fault: link lost: no SIP for 1.0 s" in reasons
    assert not outs[30].state.formed  # nobody tracks a robot stopped for its own reasons
