"""The in-process batch runner: the whole group in one process, agents called directly,
no I/O; it reads nothing of an agent but the `StepOutput` of its steps. Deterministic for
a scenario and seed.

Peer states reach the other agents `comm_delay_s` later (at least one tick): at tick k
an agent sees what the others published at tick k - d. The multi-process lockstep
runtime has the same one-tick age, which is why the two give the same trajectory.

What is the same for every robot is done for all of them at once: the world casts every
sonar ring in one pass, the readings become obstacle geometry in one pass
(`SonarGeometry.read_all`, handed to each agent in its `Observation`), and the ground
truth and commands are recorded as columns. Each agent's step is its own.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from phalanx.agents.agent import Agent, Observation, StepOutput
from phalanx.agents.control.spacing import near_radius_m, near_sets
from phalanx.agents.masking import SlotMasks, mask_readings
from phalanx.agents.perception import SonarGeometry
from phalanx.core import compiled
from phalanx.core.config import Scenario
from phalanx.core.config_files import load_robot, prior_map
from phalanx.core.formation import Formation, scenario_formation
from phalanx.core.geometry import Twist2D
from phalanx.core.peers import PeerState, Scan
from phalanx.core.robot_params import RobotParams
from phalanx.core.runlog import RobotTrace, RunLog
from phalanx.core.states import TransitionEvent
from phalanx.runtime.heap import lifelong_heap
from phalanx.simulator.world import World

FloatArray = npt.NDArray[np.float64]
ProgressCallback = Callable[[int, int], None]
StopCondition = Callable[["BatchRunner"], bool]


def build_agents(scenario: Scenario, robot: RobotParams, formation: Formation) -> dict[str, Agent]:
    """One agent per robot; in a navigating scenario all of them plan over one fleet map
    (the runner adds each step's scans to it once: the same map each would build from
    the scans shared over Zenoh).
    """
    prior = prior_map(scenario)
    agents = {
        entry.id: Agent(
            entry.id, scenario=scenario, robot=robot, formation=formation, prior_map=prior
        )
        for entry in scenario.robots
    }
    shared = next(iter(agents.values())).parts.planner.fleet
    if shared is not None:
        for agent in agents.values():
            agent.parts.planner.share(shared)
    return agents


# A fleet this large has every robot keep apart only from those near it, sorted out for
# all at once every `NEAR_REFRESH_S` (checking every other robot each step would cost
# each robot-step a pass over the whole fleet).
NEAR_FLEET = 16
NEAR_REFRESH_S = 1.0


class BatchRunner:
    """Runs a scenario to the end in this process."""

    def __init__(self, scenario: Scenario, *, robot: RobotParams | None = None) -> None:
        compiled.choice()  # (a PHALANX_KERNELS it does not know stops the run before it starts)
        self.scenario = scenario
        self.robot = robot or load_robot(scenario.robot)
        self.formation = scenario_formation(scenario)
        self.world = World.for_scenario(scenario, self.robot)
        self.agents = build_agents(scenario, self.robot, self.formation)
        # (robot i of the world is agent i: both are in the scenario's order)
        self.steps = round(scenario.duration_s * scenario.control_rate_hz)
        self.delay_ticks = max(1, round(scenario.comm_delay_s * scenario.control_rate_hz))
        self.t_s = np.arange(self.steps, dtype=np.float64) * scenario.dt_s
        self.sonar = SonarGeometry.from_params(self.robot)
        self._masks_of: tuple[SlotMasks, ...] = ()
        self._slot_masks = self._fleet_masks()
        self._scans: tuple[Scan, ...] = ()  # every robot's last step's, for the fleet map
        self._fleet_map = next(iter(self.agents.values())).parts.planner.fleet
        self._near: dict[str, frozenset[str]] = {}
        self._near_s = -np.inf
        # x, y, theta, v, omega, commanded v and omega: (column, robot, step)
        self._columns = np.zeros((7, len(self.agents), self.steps))
        self._direction = np.ones((len(self.agents), self.steps), dtype=np.int8)
        self._estimate = np.full((len(self.agents), self.steps, 3), np.nan)
        self.traces = {rid: self._trace(i) for i, rid in enumerate(self.agents)}
        self._published: deque[dict[str, PeerState]] = deque(maxlen=self.delay_ticks)
        self.transitions: dict[str, list[TransitionEvent]] = {rid: [] for rid in self.agents}
        self.last: dict[str, StepOutput] = {}
        self.done = 0

    def run(
        self, progress: ProgressCallback | None = None, *, until: StopCondition | None = None
    ) -> RunLog:
        """Step every robot to the end of the scenario (or until `until(self)` holds)."""
        started = time.perf_counter()
        # (a fifth of a 1000-robot run's time went into the collector traversing the
        # fleet, the world and the traces again and again before they were frozen)
        with lifelong_heap():
            for k in range(self.steps):
                self.step(k)
                if progress is not None:
                    progress(k + 1, self.steps)
                if until is not None and until(self):
                    break
        return self._log(time.perf_counter() - started)

    def _fleet_masks(self) -> SlotMasks:
        """Every robot's slot masks stacked (again only when a robot's changed: its
        group changed shape).
        """
        masks = tuple(agent.slot_masks for agent in self.agents.values())
        if len(masks) != len(self._masks_of) or any(
            a is not b for a, b in zip(masks, self._masks_of, strict=True)
        ):
            self._masks_of = masks
            self._slot_masks = SlotMasks.concat(masks)
        return self._slot_masks

    def _near_robots(self, peers: dict[str, PeerState], t_s: float) -> dict[str, frozenset[str]]:
        """Whom each robot of a large fleet keeps apart from (every robot, in a small
        one: an empty mapping), from where they said they were.
        """
        if len(self.agents) <= NEAR_FLEET or len(peers) < len(self.agents):
            return {}
        if t_s - self._near_s >= NEAR_REFRESH_S - 1e-9:
            spacing = next(iter(self.agents.values())).spacing
            radius = near_radius_m(
                spacing.contact_m,
                v_max_mps=self.robot.v_max_mps,
                decel_mps2=spacing.decel_mps2,
                latency_s=spacing.latency_s,
                horizon_s=NEAR_REFRESH_S,
            )
            self._near_s = t_s
            self._near = near_sets({r: (p.x_m, p.y_m) for r, p in peers.items()}, radius_m=radius)
        return self._near

    def _trace(self, i: int) -> RobotTrace:
        """Robot i's trace: its arrays are rows of the run's columns."""
        c, n = self._columns, self.steps
        trace = RobotTrace(
            c[0, i], c[1, i], c[2, i], c[3, i], c[4, i], c[5, i], c[6, i], self._direction[i]
        )
        trace.estimate, trace.cov = self._estimate[i], np.full((n, 6), np.nan)
        return trace

    def step(self, k: int) -> None:
        """Control step `k`: sense, think, record, then integrate the world."""
        t_s = float(self.t_s[k])
        world = self.world
        # Every robot's state carries its flags: peers and flags are the same mapping.
        peers = self._published[0] if len(self._published) == self.delay_ticks else {}
        commands: dict[str, Twist2D] = {}
        states: dict[str, PeerState] = {}
        truth = self._columns[:, :, k]
        truth[:5] = world.x, world.y, world.th, world.v, world.w
        outs = []
        for rid, agent, obs in self._observe(peers, t_s):
            out = agent.step(obs, peers, t_s)
            commands[rid], states[rid] = out.command, out.state
            outs.append(out)
        self._scans = tuple(out.scan for out in outs if out.scan is not None)
        self._record(k, outs)
        self._published.append(states)
        world.step(commands, self.scenario.dt_s)
        self.done = k + 1

    def _observe(
        self, peers: dict[str, PeerState], t_s: float
    ) -> list[tuple[str, Agent, Observation]]:
        """Every robot's observation: the world's readings, the sonar read as geometry
        and masked (every robot heard first: masking needs whom each tracks) in one pass.
        """
        statuses, ranges = self.world.statuses()
        readings = self.sonar.read_all(ranges).readings
        odometry = self.world.odometries()
        agents = self.agents
        near = self._near_robots(peers, t_s)
        if self._fleet_map is not None:
            # (once for all: each agent adds only its own reading, already in here)
            self._fleet_map.add(self._scans)
        observed = [
            Observation(
                odometry[i],
                statuses[i],
                readings[i],
                None,
                *self.world.positioning(rid),
                near=near.get(rid),
            )
            for i, rid in enumerate(agents)
        ]
        pairs = zip(agents.values(), observed, strict=True)
        heard = [agent.hear(obs, peers, t_s) for agent, obs in pairs]
        masked = mask_readings(self.sonar, readings, heard, self._fleet_masks())
        return [
            (rid, agent, obs.with_masked(masked[i]))
            for i, ((rid, agent), obs) in enumerate(zip(agents.items(), observed, strict=True))
        ]

    def _record(self, k: int, outs: list[StepOutput]) -> None:
        """Step `k`'s outputs, robots in order: numbers as columns, for all at once."""
        self._columns[5, :, k] = [out.command.v_mps for out in outs]
        self._columns[6, :, k] = [out.command.omega_radps for out in outs]
        self._direction[:, k] = [out.state.direction for out in outs]
        self._estimate[:, k] = [(o.state.x_m, o.state.y_m, o.state.theta_rad) for o in outs]
        for (rid, tr), out in zip(self.traces.items(), outs, strict=True):
            state = out.state
            tr.states.append(state.fsm_state)
            tr.tracked.append(state.leader_id)
            tr.leaders.append(state.formation_leader_id)
            tr.epochs.append(state.epoch)
            tr.formed.append(state.formed)
            tr.shapes.append((state.shape_source, state.shape_target, state.morph))
            tr.fits.append(state.shape_fits)
            if state.cov:
                tr.cov[k] = state.cov
            if out.events:
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
