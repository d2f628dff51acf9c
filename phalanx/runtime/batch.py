"""The in-process batch runner: the whole group in one process, agents called directly,
no I/O; it reads nothing of an agent but the `StepOutput` of its steps. Deterministic for
a scenario and seed.

Peer states reach the other agents `comm_delay_s` later (at least one tick): at tick k
an agent sees what the others published at tick k - d. The multi-process lockstep
runtime has the same one-tick age, which is why the two give the same trajectory.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from phalanx.agents.agent import Agent, Observation, StepOutput
from phalanx.core.config import RobotParams, Scenario
from phalanx.core.config_files import load_robot
from phalanx.core.formation import Formation, scenario_formation
from phalanx.core.geometry import Twist2D
from phalanx.core.peers import PeerState
from phalanx.core.runlog import RobotTrace, RunLog
from phalanx.core.states import TransitionEvent
from phalanx.simulator.world import World

FloatArray = npt.NDArray[np.float64]
ProgressCallback = Callable[[int, int], None]
StopCondition = Callable[["BatchRunner"], bool]


def build_agents(scenario: Scenario, robot: RobotParams, formation: Formation) -> dict[str, Agent]:
    """One agent per robot."""
    return {
        entry.id: Agent(entry.id, scenario=scenario, robot=robot, formation=formation)
        for entry in scenario.robots
    }


class BatchRunner:
    """Runs a scenario to the end in this process."""

    def __init__(self, scenario: Scenario, *, robot: RobotParams | None = None) -> None:
        self.scenario = scenario
        self.robot = robot or load_robot(scenario.robot)
        self.formation = scenario_formation(scenario)
        self.world = World.for_scenario(scenario, self.robot)
        self.agents = build_agents(scenario, self.robot, self.formation)
        self.steps = round(scenario.duration_s * scenario.control_rate_hz)
        self.delay_ticks = max(1, round(scenario.comm_delay_s * scenario.control_rate_hz))
        self.t_s = np.arange(self.steps, dtype=np.float64) * scenario.dt_s
        self.traces = {rid: RobotTrace.empty(self.steps) for rid in self.agents}
        self._published: deque[dict[str, PeerState]] = deque(maxlen=self.delay_ticks)
        self.transitions: dict[str, list[TransitionEvent]] = {rid: [] for rid in self.agents}
        self.last: dict[str, StepOutput] = {}
        self.done = 0

    def run(
        self, progress: ProgressCallback | None = None, *, until: StopCondition | None = None
    ) -> RunLog:
        """Step every robot to the end of the scenario (or until `until(self)` holds)."""
        started = time.perf_counter()
        for k in range(self.steps):
            self.step(k)
            if progress is not None:
                progress(k + 1, self.steps)
            if until is not None and until(self):
                break
        return self._log(time.perf_counter() - started)

    def step(self, k: int) -> None:
        """Control step `k`: sense, think, record, then integrate the world."""
        t_s = float(self.t_s[k])
        # Every robot's state carries its flags: peers and flags are the same mapping.
        peers = self._published[0] if len(self._published) == self.delay_ticks else {}
        commands: dict[str, Twist2D] = {}
        states: dict[str, PeerState] = {}
        for rid, agent in self.agents.items():
            fixes, relative = self.world.positioning(rid)
            obs = Observation(self.world.odometry(rid), self.world.status(rid), fixes, relative)
            out = agent.step(obs, peers, t_s)
            commands[rid], states[rid] = out.command, out.state
            self._record(rid, k, out)
        self._published.append(states)
        self.world.step(commands, self.scenario.dt_s)
        self.done = k + 1

    def _record(self, rid: str, k: int, out: StepOutput) -> None:
        pose, twist = self.world.truth(rid)
        tr, state, command = self.traces[rid], out.state, out.command
        tr.x_m[k], tr.y_m[k], tr.theta_rad[k] = pose.x_m, pose.y_m, pose.theta_rad
        tr.v_mps[k], tr.omega_radps[k] = twist.v_mps, twist.omega_radps
        tr.cmd_v_mps[k], tr.cmd_omega_radps[k] = command.v_mps, command.omega_radps
        tr.direction[k] = state.direction
        tr.states.append(state.fsm_state)
        tr.tracked.append(state.leader_id)
        tr.leaders.append(state.formation_leader_id)
        tr.epochs.append(state.epoch)
        tr.formed.append(state.formed)
        tr.estimate[k] = (state.x_m, state.y_m, state.theta_rad)
        if state.cov:
            tr.cov[k] = state.cov
        self.transitions[rid].extend(out.events)
        self.last[rid] = out

    def _log(self, wall_time_s: float) -> RunLog:
        n = self.done
        return RunLog(
            scenario=self.scenario,
            robot=self.robot,
            formation=self.formation,
            t_s=self.t_s[:n],
            traces={rid: tr.truncated(n) for rid, tr in self.traces.items()},
            transitions={rid: list(events) for rid, events in self.transitions.items()},
            collisions=list(self.world.collisions),
            saturations={rid: out.saturations for rid, out in self.last.items()},
            accel_limited={rid: out.accel_limited for rid, out in self.last.items()},
            wall_time_s=wall_time_s,
        )


def run_batch(
    scenario: Scenario,
    *,
    robot: RobotParams | None = None,
    progress: ProgressCallback | None = None,
) -> RunLog:
    """Run `scenario` in this process and return its log."""
    return BatchRunner(scenario, robot=robot).run(progress)
