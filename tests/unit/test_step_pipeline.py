"""A step works out where the robots it reads are once: the robot it tracks and the
formation's leader are dead-reckoned to the step's time in the fleet view
(`phalanx.agents.inputs.now`), and every stage after (slot target, sonar masking, the
controller, the emergency stop's release, "back in formation") reads that, rather than
predicting again. Counted on a column, whose tail tracks the robot ahead of it and lays
its slot out from the leader, and on a navigating wedge run by the batch runner.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import phalanx.agents.agent as agent_module
import phalanx.agents.control.ours as ours_module
import phalanx.agents.inputs as inputs_module
import phalanx.agents.shape as shape_module
from phalanx.agents.agent import Agent, Observation
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.peers import PeerState
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.runtime.batch import BatchRunner

ROBOT = load_robot("p3dx")
COLUMN = load_scenario(CONFIG_ROOT / "scenarios" / "nav_corridor_inline3.toml")
FORMATION = scenario_formation(COLUMN)
DT_S = COLUMN.dt_s
SPEED_MPS = 0.3
CLEAR = RobotStatus(sonar_ranges_m=(5.0,) * 16, bumpers=(False,), battery_v=12.6)
AGENTS_DIR = Path(agent_module.__file__).resolve().parent


def _peer(rid: str, pose: Pose2D, t_s: float) -> PeerState:
    """`rid` driving straight along x, its state stamped half a step ago."""
    return PeerState(
        robot_id=rid, seq=round(t_s / DT_S) + 1, stamp_s=t_s - DT_S / 2, x_m=pose.x_m,
        y_m=pose.y_m, theta_rad=pose.theta_rad, v_mps=SPEED_MPS, omega_radps=0.0,
        fsm_state="NAVIGATE" if rid == "r1" else "FORMATION_TRACK",
        leader_id=FORMATION.leader_of(rid) or "", formation_leader_id="r1", clear=True,
    )  # fmt: skip


class Counted:
    """Wraps a function and records what each call predicted."""

    def __init__(self, wrapped: Callable[..., Any], name: Callable[..., str]) -> None:
        self.wrapped, self.name, self.calls = wrapped, name, []

    def __call__(self, *args: Any) -> Any:
        self.calls.append(self.name(*args))
        return self.wrapped(*args)


@pytest.fixture
def counted(monkeypatch: pytest.MonkeyPatch) -> tuple[Counted, Counted]:
    """The agent's calls of `now` (by robot predicted) and every dead reckoning of a
    robot's state anywhere in a step; the controller's own fallback must not run.
    """
    perceived = Counted(inputs_module.now, lambda state, _t: state.robot_id if state else "")
    predicted = Counted(inputs_module.predict_leader, lambda *_: "predicted")
    monkeypatch.setattr(agent_module, "now", perceived)
    monkeypatch.setattr(inputs_module, "predict_leader", predicted)

    def fallback(*_: Any) -> Pose2D:
        raise AssertionError("the controller predicted the leader again")

    monkeypatch.setattr(ours_module, "predict_leader", fallback)
    return perceived, predicted


def test_a_column_s_tail_predicts_the_robot_ahead_and_the_leader_once_a_step(
    counted: tuple[Counted, Counted],
) -> None:
    perceived, predicted = counted
    tail = Agent("r3", scenario=COLUMN, robot=ROBOT, formation=FORMATION)
    steps = 60
    for k in range(steps):
        t_s = k * DT_S
        head = Pose2D(SPEED_MPS * t_s, 0.0, 0.0)
        peers = {r: _peer(r, FORMATION.slot_pose(r, head), t_s) for r in ("r1", "r2")}
        own = FORMATION.slot_pose("r3", head)
        odometry = Odometry(own, Twist2D(SPEED_MPS, 0.0), t_s)
        before, made = len(perceived.calls), len(predicted.calls)
        tail.step(Observation(odometry, CLEAR), peers, t_s)
        assert sorted(c for c in perceived.calls[before:] if c) == ["r1", "r2"], k
        assert len(predicted.calls) - made == 2, k  # one dead reckoning each, nothing else
    assert tail.state_name == "FORMATION_TRACK"
    view = tail.view
    assert view is not None
    assert view.lead is not None
    assert view.head is not None
    assert (view.lead.robot_id, view.head.robot_id) == ("r2", "r1")
    assert view.anchor_now == inputs_module.now(view.head, (steps - 1) * DT_S)


def test_a_navigating_wedge_predicts_each_tracked_robot_once_a_step(
    counted: tuple[Counted, Counted],
) -> None:
    """The batch runner's step (which masks every robot's sonar in one pass, from the
    views) on a field: two followers tracking the leader, one prediction each a step.
    """
    perceived, predicted = counted
    scenario = load_scenario(CONFIG_ROOT / "scenarios" / "nav_field_wedge3.toml")
    scenario = scenario.model_copy(update={"duration_s": 10.0})
    log = BatchRunner(scenario).run()
    steps = len(next(iter(log.traces.values())).x_m)
    named = [c for c in perceived.calls if c]
    assert named.count("r1") <= 2 * steps  # r2 and r3 each, at most once a step
    assert named.count("r1") >= 2 * (steps - 1)  # (none heard yet at the first)
    assert set(named) == {"r1"}
    assert len(predicted.calls) == len(named)


def test_a_wedge_s_followers_lay_their_slots_out_once_a_step(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The paper's wedge, run by the batch runner: each follower's slot target is laid
    out in its fleet view, and the controller aims at that one.
    """
    laid = Counted(shape_module.rigid_body_target, lambda *_: "laid")
    monkeypatch.setattr(shape_module, "rigid_body_target", laid)

    def again(*_: Any) -> Pose2D:
        raise AssertionError("the controller laid the slot out again")

    monkeypatch.setattr(ours_module, "rigid_body_target", again)
    scenario = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
    log = BatchRunner(scenario.model_copy(update={"duration_s": 20.0})).run()
    steps = len(next(iter(log.traces.values())).x_m)
    assert 2 * (steps - 1) <= len(laid.calls) <= 2 * steps  # r2 and r3 (none heard at first)
    assert set(log.traces["r2"].states) >= {"FORMATION_TRACK"}


def test_nothing_else_in_the_brain_dead_reckons_another_robot() -> None:
    users = sorted(
        str(path.relative_to(AGENTS_DIR))
        for path in AGENTS_DIR.rglob("*.py")
        if re.search(r"\bpredict_leader\b", path.read_text(encoding="utf-8"))
    )
    # the fleet view's `now`, and the controller's own fallback for a caller without it
    assert users == ["control/ours.py", "inputs.py"]
