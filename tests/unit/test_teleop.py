"""An operator drives the leader through the behaviour stack, and gives a navigating
leader a goal: the real world simulation and the real agents of the in-process batch
runner, the operator's input handed to the leader in its observation as the runtime
hands it (the last twist heard with when it was heard; a goal once).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import pytest

from phalanx.agents.agent import Agent, Observation
from phalanx.agents.inputs import OPERATOR_TIMEOUT_S, OperatorInput
from phalanx.core.config import CircleObstacle, Scenario, WorldConfig
from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_robot, load_scenario
from phalanx.core.geometry import Twist2D, Vec2
from phalanx.core.limits import run_limits
from phalanx.core.peers import PeerState
from phalanx.core.runlog import RunLog
from phalanx.core.states import State
from phalanx.runtime.batch import BatchRunner

WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
FIELD = CONFIG_ROOT / "scenarios" / "nav_field_wedge3.toml"
Script = Callable[[float], OperatorInput | None]


class Operated(BatchRunner):
    """A batch run in which an operator speaks to robot `robot_id`: `script(t_s)` is
    what the runtime would hand it at the step at `t_s`.
    """

    def __init__(self, scenario: Scenario, script: Script, robot_id: str = "r1") -> None:
        super().__init__(scenario)
        self.script, self.robot_id = script, robot_id

    def _observe(
        self, peers: dict[str, PeerState], t_s: float
    ) -> list[tuple[str, Agent, Observation]]:
        operator = self.script(t_s)
        return [
            (rid, agent, replace(obs, operator=operator) if rid == self.robot_id else obs)
            for rid, agent, obs in super()._observe(peers, t_s)
        ]


def steady(twist: Twist2D, start_s: float, end_s: float) -> Script:
    """An operator sending `twist` every step from `start_s` to `end_s` (s), then silent:
    the runtime goes on handing in the last twist, heard at the last step it came.
    """

    def script(t_s: float) -> OperatorInput | None:
        if t_s < start_s - 1e-9:
            return None
        return OperatorInput(min(t_s, end_s), twist)

    return script


def reactive_wedge(duration_s: float = 30.0, *, obstacle_x_m: float | None = None) -> Scenario:
    """The paper's wedge with the emergency stop on, optionally a post ahead of the leader."""
    scenario = apply_overrides(
        load_scenario(WEDGE), [f"duration_s={duration_s}", "navigation.reactive=true"]
    )
    if obstacle_x_m is None:
        return scenario
    post = CircleObstacle(x_m=obstacle_x_m, y_m=0.0, radius_m=0.2)
    return scenario.model_copy(update={"world": WorldConfig(circles=(post,))})


def states(log: RunLog, rid: str, from_s: float, to_s: float) -> set[str]:
    """The states robot `rid` was in between two times."""
    return {s for t, s in zip(log.t_s, log.traces[rid].states, strict=True) if from_s <= t < to_s}


def commands(log: RunLog, rid: str, from_s: float, to_s: float) -> list[tuple[float, float]]:
    """Robot `rid`'s commands (m/s, rad/s) between two times."""
    trace = log.traces[rid]
    return [
        (float(v), float(w))
        for t, v, w in zip(log.t_s, trace.cmd_v_mps, trace.cmd_omega_radps, strict=True)
        if from_s <= t < to_s
    ]


def test_the_operator_drives_the_leader_and_the_group_keeps_its_shape() -> None:
    scenario = reactive_wedge()
    log = Operated(scenario, steady(Twist2D(0.1, 0.1), 5.0, 20.0)).run()
    assert states(log, "r1", 5.05, 20.0) == {State.TELEOP}
    for v, w in commands(log, "r1", 8.0, 20.0):  # after the limiter's ramp: as asked
        assert v == pytest.approx(0.1, abs=1e-6)
        assert w == pytest.approx(0.1, abs=1e-6)
    for rid in ("r2", "r3"):
        assert states(log, rid, 10.0, 20.0) == {State.FORMATION_TRACK}
        i = round(19.9 / scenario.dt_s)  # a follower is 1 m from the leader, on its slot
        trace, lead = log.traces[rid], log.traces["r1"]
        gap_m = math.hypot(trace.x_m[i] - lead.x_m[i], trace.y_m[i] - lead.y_m[i])
        assert gap_m == pytest.approx(1.0, abs=0.1)
    assert not log.collisions


def test_commands_that_stop_hand_the_leader_back_to_its_plan_after_half_a_second() -> None:
    log = Operated(reactive_wedge(), steady(Twist2D(0.1, 0.0), 5.0, 10.0)).run()
    back = [e for e in log.transitions["r1"] if e.source == State.TELEOP]
    assert len(back) == 1
    assert back[0].target == State.NAVIGATE
    assert back[0].reason.startswith("the operator's commands stopped")
    assert back[0].t_s == pytest.approx(10.0 + OPERATOR_TIMEOUT_S)
    assert states(log, "r1", 10.6, 30.0) == {State.NAVIGATE}  # the script again
    assert commands(log, "r1", 15.0, 30.0)[-1] == pytest.approx((0.15, 0.0))


def test_a_command_beyond_the_limits_is_limited() -> None:
    scenario = reactive_wedge()
    limits = run_limits(load_robot(scenario.robot), scenario.limits)
    log = Operated(scenario, steady(Twist2D(2.0, -3.0), 5.0, 25.0)).run()
    driven = commands(log, "r1", 5.0, 25.0)
    assert states(log, "r1", 5.05, 25.0) == {State.TELEOP}
    assert all(abs(v) <= limits.v_max_mps + 1e-9 for v, _ in driven)
    assert all(abs(w) <= limits.omega_max_radps + 1e-9 for _, w in driven)
    assert max(v for v, _ in driven) > 0.05  # it did drive the way it was asked
    assert min(w for _, w in driven) < -0.05
    assert not log.collisions


def test_the_emergency_stop_outranks_the_operator_until_asked_away_from_the_obstacle() -> None:
    # The operator drives the leader at a post 3 m ahead, keeps asking after the stop,
    # then asks it back.
    forwards, backwards = Twist2D(0.3, 0.0), Twist2D(-0.1, 0.0)

    def script(t_s: float) -> OperatorInput | None:
        if t_s < 2.0:
            return None
        return OperatorInput(t_s, forwards if t_s < 25.0 else backwards)

    log = Operated(reactive_wedge(35.0, obstacle_x_m=3.0), script).run()
    stops = [e for e in log.transitions["r1"] if e.target == State.EMERGENCY_STOP]
    assert stops
    assert stops[0].source == State.TELEOP
    assert stops[0].t_s < 25.0
    standing = states(log, "r1", stops[0].t_s + 2.0, 25.0)
    assert standing == {State.EMERGENCY_STOP}  # asked on, it does not move
    assert all(abs(v) < 1e-9 for v, _ in commands(log, "r1", stops[0].t_s + 2.0, 25.0))
    lead = log.traces["r1"]
    nearest_m = min(math.hypot(x - 3.0, y) for x, y in zip(lead.x_m, lead.y_m, strict=True))
    assert nearest_m > 0.2 + load_robot("p3dx").radius_m  # short of the post
    assert not log.collisions
    assert State.TELEOP in states(log, "r1", 25.0, 35.0)  # asked back: it backs away
    assert min(v for v, _ in commands(log, "r1", 26.0, 35.0)) < -0.05


def test_without_an_operator_nothing_changes_and_a_follower_is_not_driven() -> None:
    scenario = reactive_wedge(20.0)
    alone = BatchRunner(scenario).run()
    silent = Operated(scenario, lambda t_s: None).run()
    to_r2 = Operated(scenario, steady(Twist2D(0.3, 0.5), 2.0, 20.0), robot_id="r2").run()
    for log in (silent, to_r2):
        for rid, trace in alone.traces.items():
            assert (log.traces[rid].x_m == trace.x_m).all()
            assert (log.traces[rid].cmd_v_mps == trace.cmd_v_mps).all()
            assert log.traces[rid].states == trace.states


def goal_at(goal: Vec2, at_s: float, then: tuple[Vec2, float] | None = None) -> Script:
    """An operator sending `goal` once, at `at_s` (and the second goal of `then` at its time)."""

    def script(t_s: float) -> OperatorInput | None:
        for point, when in ((goal, at_s), *([then] if then else [])):
            if abs(t_s - when) < 1e-6:
                return OperatorInput(t_s, goal=point)
        return None

    return script


def open_field(duration_s: float) -> Scenario:
    """Three robots going to (24, 0) over open ground."""
    scenario = apply_overrides(load_scenario(FIELD), [f"duration_s={duration_s}"])
    return scenario.model_copy(update={"world": WorldConfig()})


def test_a_goal_takes_the_place_of_a_navigating_leaders_waypoints() -> None:
    first, second = Vec2(4.0, 4.0), Vec2(0.0, 7.0)
    runner = Operated(open_field(150.0), goal_at(first, 3.0, (second, 90.0)))
    log = runner.run()
    lead = log.traces["r1"]
    arrived = [e for e in log.transitions["r1"] if e.target == State.ARRIVED]
    assert len(arrived) == 2, log.transitions["r1"]
    tolerance_m = runner.scenario.navigation.goal_tolerance_m
    for event, goal in zip(arrived, (first, second), strict=True):
        i = round(event.t_s / runner.scenario.dt_s)
        assert math.hypot(lead.x_m[i] - goal.x_m, lead.y_m[i] - goal.y_m) < tolerance_m + 0.05
    assert arrived[0].t_s < 90.0
    again = [e for e in log.transitions["r1"] if e.source == State.ARRIVED]
    assert again[0].target == State.NAVIGATE
    assert again[0].reason == "a new goal"
    assert max(lead.x_m) < 6.0  # never made for the scenario's (24, 0)
    assert runner.agents["r1"].parts.route.waypoints == ((4.0, 4.0), (0.0, 7.0))


def test_a_goal_off_the_map_or_for_a_wandering_leader_is_not_taken() -> None:
    runner = Operated(open_field(5.0), goal_at(Vec2(500.0, 0.0), 1.0))
    runner.run()
    assert runner.agents["r1"].parts.route.waypoints == ((24.0, 0.0),)
    wander = open_field(5.0).model_copy(
        update={"navigation": open_field(5.0).navigation.model_copy(update={"waypoints": ()})}
    )
    runner = Operated(wander, goal_at(Vec2(2.0, 2.0), 1.0))
    log = runner.run()
    assert runner.agents["r1"].parts.route.waypoints == ()
    assert set(log.traces["r1"].states) <= {State.WANDER}
