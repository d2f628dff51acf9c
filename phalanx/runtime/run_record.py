"""A run of processes as the world process writes it down: every robot's motion tick by
tick (where the world has it, and the command it moved by), then, once the run is over,
what the robots published (their behaviour states, whom they tracked, their estimates),
the robots that move on their own from their best pose source, and whether the run is
whole. While the run goes on, `head` copies the ticks run so far for a checkpoint.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence

import numpy as np

from phalanx.core.config import Scenario
from phalanx.core.formation import Formation
from phalanx.core.geometry import Twist2D
from phalanx.core.robot_params import RobotParams
from phalanx.core.runlog import SIMULATED_POSE, FloatArray, RobotTrace, RunLog
from phalanx.core.shapes import ShapeKey
from phalanx.core.states import State, TransitionEvent
from phalanx.runtime.observed import ObservedRobots
from phalanx.simulator.world import World
from phalanx.telemetry.stream import Telemetry
from phalanx.wire.messages import AgentEvent, AgentReport, RobotState

# Each robot's last published pose (n x 3), v and omega, per tick (a tick it published
# nothing for: those it published before).
Published = dict[str, tuple[FloatArray, FloatArray, FloatArray]]
# The shape a robot is in before it has published one: a `ShapeKey`'s default (the
# scenario's, settled), as the traces hold it.
_SETTLED = ShapeKey()


class RunRecord:
    """The traces of a run of `scenario` by robots `ids`, filled in as it goes."""

    def __init__(self, scenario: Scenario, formation: Formation, ids: tuple[str, ...]) -> None:
        self.scenario, self.formation, self.ids = scenario, formation, ids
        self.steps = round(scenario.duration_s * scenario.control_rate_hz)
        self.t_s = np.arange(self.steps, dtype=np.float64) * scenario.dt_s
        self.traces = {rid: RobotTrace.empty(self.steps) for rid in ids}

    def head(self, ticks: int) -> RunRecord:
        """A copy of the first `ticks` ticks (a checkpoint's: this record goes on)."""
        part = copy.copy(self)
        part.steps, part.t_s = ticks, self.t_s[:ticks].copy()
        part.traces = {rid: copy.deepcopy(tr.truncated(ticks)) for rid, tr in self.traces.items()}
        return part

    def record(
        self, k: int, world: World, commands: Mapping[str, Twist2D], telemetry: Telemetry | None
    ) -> None:
        """Tick `k`: every robot where the world has it, and the command it moved by."""
        for rid in self.ids:
            pose, twist = world.truth(rid)
            tr = self.traces[rid]
            tr.x_m[k], tr.y_m[k], tr.theta_rad[k] = pose.x_m, pose.y_m, pose.theta_rad
            tr.v_mps[k], tr.omega_radps[k] = twist.v_mps, twist.omega_radps
            tr.cmd_v_mps[k], tr.cmd_omega_radps[k] = commands[rid].v_mps, commands[rid].omega_radps
            if telemetry is not None:
                telemetry.log_truth(rid, t_s=float(self.t_s[k]), pose=pose)

    def log(
        self,
        robot: RobotParams,
        *,
        states: Mapping[str, Mapping[int, RobotState]],
        events: Sequence[AgentEvent],
        reports: Mapping[str, AgentReport],
        observed: ObservedRobots | None,
        world: World,
        runtime: dict[str, object],
        wall_time_s: float,
    ) -> RunLog:
        """The whole run's log, once it is over."""
        published = self._take_states(states)
        sources = dict.fromkeys(self.ids, SIMULATED_POSE)
        if observed is not None:
            sources |= self._take_observed(observed, published)
        return RunLog(
            scenario=self.scenario,
            robot=robot,
            formation=self.formation,
            t_s=self.t_s,
            traces=self.traces,
            transitions=self._transitions(events),
            collisions=list(world.collisions),
            saturations={r: reports[r].saturations if r in reports else 0 for r in self.ids},
            accel_limited={r: reports[r].accel_limited if r in reports else 0 for r in self.ids},
            wall_time_s=wall_time_s,
            runtime=runtime,
            pose_sources=sources,
        )

    def _transitions(self, events: Sequence[AgentEvent]) -> dict[str, list[TransitionEvent]]:
        out: dict[str, list[TransitionEvent]] = {rid: [] for rid in self.ids}
        for e in sorted(events, key=lambda e: e.t_s):
            if e.robot_id in out:
                out[e.robot_id].append(TransitionEvent(e.t_s, e.source, e.target, e.reason))
        return out

    def _take_states(self, states: Mapping[str, Mapping[int, RobotState]]) -> Published:
        """What each robot published, tick by tick (a missing state: the one before):
        its behaviour state, whom it tracked, the leader and epoch it knew, the shape it
        was in and whether its map showed the scenario's shape fitting; its pose (its
        estimate) and covariance only at the ticks it published them for (an agent late
        on a loaded machine skips ticks, and its pose of three ticks before is not its
        estimate now); its poses and twists as held, returned.
        """
        root = self.formation.root
        published = {}
        for rid in self.ids:
            got, tr = states.get(rid, {}), self.traces[rid]
            held = np.full((self.steps, 3), np.nan)
            v, w = np.zeros(self.steps), np.zeros(self.steps)
            last = None
            tr.shapes.clear()
            tr.fits.clear()
            for trace_list in (tr.states, tr.tracked, tr.leaders, tr.epochs, tr.formed):
                trace_list.clear()
            for k in range(self.steps):
                last = got.get(k, last)
                tr.states.append(last.fsm_state if last else str(State.HOLD))
                tr.direction[k] = last.direction if last else 1
                tr.tracked.append(last.leader_id if last else (self.formation.leader_of(rid) or ""))
                tr.leaders.append(last.formation_leader_id or root if last else root)
                tr.epochs.append(last.epoch if last else 0)
                tr.formed.append(last.formed if last else True)
                tr.shapes.append(
                    (last.shape_source, last.shape_target, last.morph)
                    if last
                    else (_SETTLED.source, _SETTLED.target, _SETTLED.morph)
                )
                tr.fits.append(last.shape_fits if last else True)
                if last is None:
                    continue
                held[k] = (last.x_m, last.y_m, last.theta_rad)
                v[k], w[k] = last.v_mps, last.omega_radps
                if k in got:  # the pose it published for this tick (its estimate)
                    tr.estimate[k] = held[k]
                    if last.cov:
                        tr.cov[k] = last.cov
            published[rid] = (held, v, w)
        return published

    def _take_observed(self, observed: ObservedRobots, published: Published) -> dict[str, str]:
        """The robots that move on their own, from their best pose source interpolated
        at the ticks (heard of by no source: what they published, their own estimate),
        with the commands they published; the source of each.
        """
        sources = {}
        for rid in observed.ids:
            source, rows = observed.record(rid, self.t_s)
            tr = self.traces[rid]
            held, v, w = published[rid]
            if rows is None:
                rows = (*held.T, v, w)
            tr.x_m, tr.y_m, tr.theta_rad, tr.v_mps, tr.omega_radps = (np.array(r) for r in rows)
            tr.cmd_v_mps, tr.cmd_omega_radps = v, w
            sources[rid] = source
        return sources


def done_when_it_left(
    robot_id: str, tick: int, reports: Mapping[str, AgentReport], steps: int
) -> bool:
    """Whether a robot whose liveliness went at `tick` had ended its run: it reported,
    and left at the last tick or after. On its own clock it ends its last step as the
    world does, so it may leave before the world's last frame.
    """
    return robot_id in reports and tick >= steps - 1


def completeness(
    *,
    steps: int,
    ticks_run: int,
    absent: Sequence[str],
    lost: Sequence[tuple[str, int]],
    reports: Mapping[str, AgentReport],
    ids: Sequence[str],
) -> dict[str, object]:
    """Whether a run is whole: every tick run, no robot gone, every report in. A robot
    that left when its run was done (`done_when_it_left`) is not gone.
    """
    gone = [(r, k) for r, k in lost if not done_when_it_left(r, k, reports, steps)]
    reasons = []
    if ticks_run < steps:
        reasons.append(f"the world ran {ticks_run} of {steps} ticks")
    reasons += [f"robot {r} was not there at the start" for r in absent]
    reasons += [f"robot {r} went away at tick {k}" for r, k in gone]
    missing = sorted(set(ids) - set(reports))
    if missing:
        reasons.append(f"no report from {', '.join(missing)}")
    return {
        "ticks_run": ticks_run,
        "lost": [{"robot": r, "tick": k} for r, k in gone],
        "absent": list(absent),
        "complete": not reasons,
        "incomplete_reason": "; ".join(reasons),
    }
