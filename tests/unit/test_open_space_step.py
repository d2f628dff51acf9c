"""A sonar reading without an echo (open space: every range at the ring's maximum) takes
a short way through the sense stage: the reading is kept while the ranges stay the same,
and there is nothing to mask. A follower stepped on its own that way steps, bit for bit,
as one handed the reading and its masking worked out in full, whatever readings come,
with echoes or without, in any order.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from phalanx.agents import masking
from phalanx.agents.agent import Agent, Observation, StepOutput
from phalanx.agents.perception import SonarGeometry
from phalanx.agents.sensing import Sensing
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.peers import PeerState
from phalanx.core.robot import Odometry, RobotStatus
from phalanx.runtime.batch import BatchRunner

ROBOT = load_robot("p3dx")
WEDGE = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
FORMATION = scenario_formation(WEDGE)
SONAR = SonarGeometry.from_params(ROBOT)
TOP_M = ROBOT.sonar.max_range_m
OPEN = (TOP_M,) * len(ROBOT.sonar.units)
# r2's ring at the start of the paper's run: r1 and r3 heard on several transducers
HEARD = BatchRunner(WEDGE).world.statuses()[0][1].sonar_ranges_m
BEYOND = (TOP_M + 0.5, *OPEN[1:])  # (a range past the maximum is no echo either)
READINGS = [OPEN, OPEN, tuple(OPEN), HEARD, OPEN, BEYOND, BEYOND, HEARD, HEARD, OPEN, OPEN]


def _leader(t_s: float) -> PeerState:
    """r1 driving along x at 0.15 m/s, its state a step old."""
    stamp_s = t_s - WEDGE.dt_s
    return PeerState(
        robot_id="r1", seq=round(t_s / WEDGE.dt_s) + 1, stamp_s=stamp_s, x_m=0.15 * stamp_s,
        y_m=0.0, theta_rad=0.0, v_mps=0.15, omega_radps=0.0, fsm_state="NAVIGATE",
        formation_leader_id="r1", clear=True,
    )  # fmt: skip


def _spy(agent: Agent, seen: list[Sensing]) -> None:
    """Keep every `Sensing` the agent's sense stage gives."""
    read = agent.parts.senses.read

    def spied(*args: Any, **kwargs: Any) -> Sensing:
        sensing = read(*args, **kwargs)
        seen.append(sensing)
        return sensing

    agent.parts.senses.read = spied  # type: ignore[method-assign]


def _worked_out(agent: Agent, observation: Observation, peers: Any, t_s: float) -> StepOutput:
    """`agent`'s step with its reading and its masking worked out in full beforehand, as
    the batch runner hands them in.
    """
    reading = SONAR.read(observation.status.sonar_ranges_m)
    observation = Observation(observation.odometry, observation.status, reading)
    inputs = agent.hear(observation, peers, t_s)
    batch = masking._batch_of([reading])
    mask = masking._masked(SONAR, batch, [inputs], agent.slot_masks)[0]
    return agent.step(observation.with_masked(mask), peers, t_s)


@pytest.mark.parametrize("follower", ["r2", "r3"])
def test_a_follower_in_open_space_steps_as_the_full_arithmetic_steps_it(follower: str) -> None:
    alone, full = (Agent(follower, scenario=WEDGE, robot=ROBOT, formation=FORMATION) for _ in "ab")
    seen_alone: list[Sensing] = []
    seen_full: list[Sensing] = []
    _spy(alone, seen_alone)
    _spy(full, seen_full)
    at = FORMATION.positions[follower]
    for k, ranges in enumerate(READINGS * 3):
        t_s = (k + 1) * WEDGE.dt_s
        odometry = Odometry(Pose2D(at.x_m + 0.01 * k, at.y_m, 0.0), Twist2D(0.15, 0.0), t_s)
        observation = Observation(odometry, RobotStatus(sonar_ranges_m=ranges))
        peers = {"r1": _leader(t_s)}
        assert alone.step(observation, peers, t_s) == _worked_out(full, observation, peers, t_s)
        a, b = seen_alone[-1], seen_full[-1]
        for got, want in zip((*a.points, *a.raw), (*b.points, *b.raw), strict=True):
            assert np.array_equal(got, want)
            assert got.dtype == want.dtype
        assert (a.ahead_m, a.blocked, a.path_clear, a.imminent) == (
            b.ahead_m,
            b.blocked,
            b.path_clear,
            b.imminent,
        )
    assert alone.state_name == "FORMATION_TRACK"
    assert any(s.raw[0].size for s in seen_alone)  # (the echoes were heard)
