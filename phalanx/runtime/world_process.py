"""The world as a process: owns ground truth, sensors and collisions; drives every robot
on the `sim` driver over Zenoh; runs in lockstep or in real time; writes the run's log.

Lockstep: for each tick the world sends every robot its SenseFrame, waits (bounded) for
every live robot's RobotState of that tick, then integrates. The state is the robot's
answer: its twist is the command the robot executes from the tick on (a lockstep world
hears no VelocityCommand). A robot that misses the deadline is reported and stands
still for that tick; nobody waits forever. The next frames carry the states to the
other robots (`SenseFrame.peers`): an agent sends one message a tick and hears one,
whatever the fleet's size.
Real time: the world integrates on the wall clock (optionally sped up) with the latest
commands it has.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from phalanx.core.config import RobotParams, Scenario
from phalanx.core.errors import ConfigError
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import ZERO_TWIST, Twist2D
from phalanx.core.limits import KinematicLimits
from phalanx.core.runlog import RobotTrace, RunLog
from phalanx.core.states import State, TransitionEvent
from phalanx.runtime.signals import Stoppable
from phalanx.runtime.world_frames import (
    Flat,
    lockstep_frame_bytes,
    publish_positioning,
    send_final,
    sense_frame,
)
from phalanx.runtime.world_inbox import WorldInbox
from phalanx.simulator.world import World
from phalanx.telemetry.stream import PAPER_ANGULAR_BOUND_PCT, PAPER_LINEAR_BOUND_PCT, Telemetry
from phalanx.wire.bounds import FleetBounds
from phalanx.wire.keys import (
    alive_key,
    alive_pattern,
    leader_key,
    robot_key,
    robots_key,
    status_key,
)
from phalanx.wire.messages import (
    AgentEvent,
    AgentReport,
    LeaderAnnouncement,
    RobotState,
    VelocityCommand,
)
from phalanx.wire.relink import Relinker
from phalanx.wire.transport import (
    LOWLATENCY_MAX_BYTES,
    FleetSession,
    TransportConfig,
    open_session,
)

log = logging.getLogger("phalanx.world")
WORLD_ID = "world"
# Commands and states are kept for ticks up to this far ahead of the world's (a late one
# is fine; one for a tick this far off is no agent's, and would only take memory).
AHEAD_S = 2.0
# At the end: the final frame is sent again this often (s) to a robot whose report is not
# in, and one whose liveliness went this recently (s) is still waited for: past the 5 s a
# deaf robot waits before it re-opens its session, and the 2 s that takes at most.
FINAL_RESEND_S = 1.0
REPORT_GRACE_S = 10.0


@dataclass
class WorldOptions:
    """How the world process runs."""

    fleet: str
    transport: TransportConfig
    clock: Literal["lockstep", "realtime"] = "lockstep"
    speed: float = 1.0
    tick_timeout_s: float = 2.0
    startup_timeout_s: float = 60.0
    report_timeout_s: float = 12.0  # (waited only while a report is missing)
    epoch_s: float | None = None  # real time: tick 0 at this Unix time (shared with agents)


class WorldProcess:
    """Simulates the scenario's world for agents in other processes."""

    def __init__(
        self,
        scenario: Scenario,
        robot: RobotParams,
        options: WorldOptions,
        *,
        telemetry: Telemetry | None = None,
    ) -> None:
        self.scenario, self.robot, self.options = scenario, robot, options
        self.telemetry = telemetry
        self.world = World.for_scenario(scenario, robot)
        self.formation = scenario_formation(scenario)
        self.bounds = FleetBounds.of(scenario, robot)
        self.ids = tuple(r.id for r in scenario.robots)
        self.steps = round(scenario.duration_s * scenario.control_rate_hz)
        self.t_s = np.arange(self.steps, dtype=np.float64) * scenario.dt_s
        self.traces = {rid: RobotTrace.empty(self.steps) for rid in self.ids}
        self.inbox = WorldInbox(self.ids)
        self.missed: dict[str, int] = dict.fromkeys(self.ids, 0)
        self.tick = 0
        self.ticks_run = 0
        self.started = False  # past the start, a robot that goes away is lost to the run
        self.absent: tuple[str, ...] = ()  # robots not there when the run started
        self._fabric: FleetSession | None = None  # the session, once open
        self.wall_time_s = 0.0
        self.overruns = 0  # real time: ticks whose work outlasted the period
        self._ahead_ticks = max(2, round(AHEAD_S / scenario.dt_s))
        if options.clock == "lockstep" and options.transport.lowlatency:
            self._check_frames_fit()

    def _check_frames_fit(self) -> None:
        """On the low-latency transport (messages up to LOWLATENCY_MAX_BYTES) refuse,
        before anything runs, a fleet whose lockstep frames would not fit, rather than
        fail at its first full tick.
        """
        size = lockstep_frame_bytes(self.world, self.ids, self.scenario.dt_s)
        if size > LOWLATENCY_MAX_BYTES:
            raise ConfigError(
                f"{len(self.ids)} robots: a lockstep frame with every other robot's state is "
                f"{size} bytes, over the low-latency transport's {LOWLATENCY_MAX_BYTES}: "
                "run the fleet's processes without --lowlatency"
            )

    def run(self, stop: Stoppable) -> RunLog:
        """Run the scenario to its end (or `stop`) and return the log."""
        with (
            open_session(self.options.transport) as session,
            Relinker(session, lambda: self.inbox.heard_s) as relinker,
        ):
            self._wire(session)
            relinker.start()  # (a world that is its fleet's router has nothing to re-open)
            self._log_static()
            self._await_agents(stop)
            period_s = self.scenario.dt_s / self.options.speed
            epoch = self.options.epoch_s
            if self.options.clock == "realtime" and epoch is not None:
                stop.wait(max(0.0, epoch - time.time()))
            started = time.perf_counter()
            next_tick = time.monotonic()
            for k in range(self.steps):
                if stop.is_set():
                    break
                self._tick(session, k)
                if self.options.clock == "realtime":
                    next_tick += period_s
                    slack = next_tick - time.monotonic()
                    if slack < 0.0:
                        self.overruns += 1
                        next_tick = time.monotonic()  # do not try to catch up in a burst
                    time.sleep(max(0.0, slack))
            self.wall_time_s = time.perf_counter() - started
            self._finish(session)
        return self._log()

    @property
    def stats(self) -> Any:
        """The session's DecodeStats (None until it is open)."""
        return self._fabric.stats if self._fabric is not None else None

    def _wire(self, session: FleetSession) -> None:
        fleet, bounds = self.options.fleet, self.bounds
        self._fabric = session
        session.declare_alive(alive_key(fleet, WORLD_ID))
        subscriptions = [
            (robots_key(fleet, "state"), RobotState, self._on_state),
            (robots_key(fleet, "event"), AgentEvent, self._on_event),
            (robots_key(fleet, "report"), AgentReport, self._on_report),
            (leader_key(fleet), LeaderAnnouncement, self._on_leader),
        ]
        if self.options.clock == "realtime":  # (in lockstep a robot's state is its command)
            subscriptions.append((robots_key(fleet, "cmd"), VelocityCommand, self._on_command))
        for key, model, handler in subscriptions:
            session.subscribe(key, model, handler, context=bounds)  # type: ignore[arg-type]
        session.watch_alive(alive_pattern(fleet), self._on_alive)
        session.serve_status(status_key(fleet, WORLD_ID), self._status)

    def _too_far_ahead(self, tick: int, name: str, robot_id: str) -> bool:
        """Whether `tick` is beyond the window kept (then counted as refused)."""
        if tick <= self.tick + self._ahead_ticks:
            return False
        if self.stats is not None:
            self.stats.count("rejected", name, f"{name} of {robot_id} for tick {tick}")
        return True

    # (The session has checked every message: a robot of this fleet, on its own key.)
    def _on_command(self, _key: str, cmd: VelocityCommand) -> None:
        if not self._too_far_ahead(cmd.tick, "VelocityCommand", cmd.robot_id):
            with self.inbox.cond:
                self.inbox.heard(cmd.robot_id, cmd.tick, self.tick)
                self.inbox.answer(cmd.robot_id, cmd.tick, Twist2D(cmd.v_mps, cmd.omega_radps))

    def _on_state(self, _key: str, state: RobotState) -> None:
        tick = round(state.stamp_s / self.scenario.dt_s)
        if tick < self.steps and not self._too_far_ahead(tick, "RobotState", state.robot_id):
            with self.inbox.cond:
                self.inbox.heard(state.robot_id, tick, self.tick)
                self.inbox.states[state.robot_id][tick] = state
                if self.options.clock == "lockstep":  # the state is the robot's answer
                    twist = Twist2D(state.v_mps, state.omega_radps)
                    self.inbox.answer(state.robot_id, tick, twist)

    def _on_event(self, _key: str, event: AgentEvent) -> None:
        with self.inbox.cond:
            self.inbox.keep(self.inbox.events, event)

    def _on_leader(self, _key: str, announcement: LeaderAnnouncement) -> None:
        with self.inbox.cond:
            self.inbox.keep(self.inbox.leaders, announcement)

    def _on_report(self, _key: str, report: AgentReport) -> None:
        with self.inbox.cond:
            self.inbox.reports[report.robot_id] = report
            self.inbox.cond.notify_all()

    def _on_alive(self, key: str, alive: bool) -> None:
        robot = key.rsplit("/", 1)[-1]
        if robot not in self.traces:
            return  # another process (a tool, the world itself) or no robot of this fleet
        with self.inbox.cond:
            (self.inbox.alive.add if alive else self.inbox.alive.discard)(robot)
            if not alive:
                self.inbox.gone(robot, self.tick if self.started else None)
            self.inbox.cond.notify_all()
        if not alive:
            log.warning("robot %s is gone (liveliness lost)", robot)

    def _status(self) -> dict[str, object]:
        stats = self.stats.as_dict() if self.stats is not None else {}
        return {
            "tick": self.tick,
            "missed": self.missed,
            "alive": sorted(self.inbox.alive),
            "lost": [{"robot": r, "tick": k} for r, k in self.inbox.lost],
            "log_overflow": self.inbox.overflow,
            "dropped": stats.get("dropped", 0),
            "relinks": self._fabric.relinks if self._fabric is not None else 0,
            "decode": stats,
        }

    def _await_agents(self, stop: Stoppable) -> None:
        """Wait for every robot (up to the startup timeout), then start the run with
        those there: one not there (gone before the start, or never come) is marked
        absent in the run's results; from the start on, one that goes away is lost.
        """
        deadline = time.monotonic() + self.options.startup_timeout_s
        with self.inbox.cond:
            while not set(self.ids) <= self.inbox.alive and not stop.is_set():
                remaining = deadline - time.monotonic()
                if remaining <= 0.0:
                    break
                self.inbox.cond.wait(min(0.2, remaining))
            everyone = set(self.ids) <= self.inbox.alive
        if everyone:
            time.sleep(0.2)  # let the agents' subscriptions reach the world's publications
        with self.inbox.cond:
            self.started = True
            self.absent = tuple(r for r in self.ids if r not in self.inbox.alive)
        if self.absent:
            log.warning("starting without %s", list(self.absent))

    def _positioning(self, session: FleetSession, rid: str) -> Flat:
        fixes, relative = self.world.positioning(rid)
        epoch, fleet = self.options.epoch_s, self.options.fleet
        return publish_positioning(session, fleet, rid, fixes, relative, self.ids, epoch_s=epoch)

    def _tick(self, session: FleetSession, k: int) -> None:
        self.tick = k
        self.ticks_run += 1
        with self.inbox.cond:
            self.inbox.sent_at[k] = time.monotonic()
            self.inbox.sent_at.pop(k - 50, None)
        self.world.sense_all()  # every robot's sonar in one pass; each frame reads its row
        lockstep = self.options.clock == "lockstep"
        # (a state older than the window kept ahead is no news either)
        relay = self.inbox.relay(k, self._ahead_ticks) if lockstep else ()
        for rid in self.ids:
            session.publish(
                robot_key(self.options.fleet, rid, "sense"),
                sense_frame(
                    self.world,
                    rid,
                    k,
                    self.scenario.dt_s,
                    positioning=self._positioning(session, rid),
                    peers=tuple(s for s in relay if s.robot_id != rid),
                ),
                reliable_block=True,
            )
        if lockstep:
            self._await_states(k)
        commands = self._commands_for(k)
        self._record(k, commands)
        self.world.step(commands, self.scenario.dt_s)

    def _await_states(self, k: int) -> None:
        for rid in self.inbox.await_states(k, self.options.tick_timeout_s):
            self.missed[rid] += 1
            log.warning("robot %s missed the deadline of tick %d", rid, k)

    def _commands_for(self, k: int) -> dict[str, Twist2D]:
        with self.inbox.cond:
            got = self.inbox.commands.pop(k, {})
            latest = dict(self.inbox.latest)
        out = {}
        for rid in self.ids:
            cmd = got.get(rid) if self.options.clock == "lockstep" else latest.get(rid)
            out[rid] = cmd if cmd is not None and rid in self.inbox.alive else ZERO_TWIST
        return out

    def _log_static(self) -> None:
        """Obstacles, the paper's bounds and the velocity limits, the layout."""
        if self.telemetry is None:
            return
        world = self.scenario.world
        self.telemetry.log_world(
            circles=[(c.x_m, c.y_m, c.radius_m) for c in world.circles],
            polygons=[list(p.vertices_m) for p in world.polygons],
        )
        limits = KinematicLimits.from_params(self.robot, self.scenario.limits)
        self.telemetry.log_bounds(
            t_s=[0.0, self.scenario.duration_s],
            linear_pct=PAPER_LINEAR_BOUND_PCT,
            angular_pct=PAPER_ANGULAR_BOUND_PCT,
            v_max_mps=limits.v_max_mps,
            omega_max_radps=limits.omega_max_radps,
        )
        self.telemetry.send_blueprint(self.ids)

    def _record(self, k: int, commands: dict[str, Twist2D]) -> None:
        for rid in self.ids:
            pose, twist = self.world.truth(rid)
            tr = self.traces[rid]
            tr.x_m[k], tr.y_m[k], tr.theta_rad[k] = pose.x_m, pose.y_m, pose.theta_rad
            tr.v_mps[k], tr.omega_radps[k] = twist.v_mps, twist.omega_radps
            tr.cmd_v_mps[k], tr.cmd_omega_radps[k] = commands[rid].v_mps, commands[rid].omega_radps
            if self.telemetry is not None:
                self.telemetry.log_truth(rid, t_s=float(self.t_s[k]), pose=pose)

    def _finish(self, session: FleetSession) -> None:
        """The final frame, again to robots whose report is not in (`await_reports`)."""
        fleet, k, dt_s = self.options.fleet, self.tick, self.scenario.dt_s
        self.inbox.await_reports(
            lambda robots: send_final(session, self.world, fleet, robots, k, dt_s),
            timeout_s=self.options.report_timeout_s, every_s=FINAL_RESEND_S, grace_s=REPORT_GRACE_S,
        )  # fmt: skip

    def _log(self) -> RunLog:
        self._fill_states()
        reports = self.inbox.reports
        events: dict[str, list[TransitionEvent]] = {rid: [] for rid in self.ids}
        for e in sorted(self.inbox.events, key=lambda e: e.t_s):
            if e.robot_id in events:
                events[e.robot_id].append(TransitionEvent(e.t_s, e.source, e.target, e.reason))
        return RunLog(
            scenario=self.scenario,
            robot=self.robot,
            formation=self.formation,
            t_s=self.t_s,
            traces=self.traces,
            transitions=events,
            collisions=list(self.world.collisions),
            saturations={r: reports[r].saturations if r in reports else 0 for r in self.ids},
            accel_limited={r: reports[r].accel_limited if r in reports else 0 for r in self.ids},
            wall_time_s=self.wall_time_s,
            runtime=self._runtime(),
        )

    def _runtime(self) -> dict[str, object]:
        """Figures of the run as processes: response times, deadlines, reports."""
        period_s = self.scenario.dt_s / self.options.speed
        response = np.asarray(self.inbox.response_s, dtype=np.float64)
        quantiles: list[float | None] = (
            np.quantile(response, [0.5, 0.99]).tolist() if response.size else [None, None]
        )
        expected = (self.tick + 1) * len(self.ids)
        return {
            "clock": self.options.clock,
            "period_s": period_s,
            "response_p50_s": quantiles[0],
            "response_p99_s": quantiles[1],
            "response_max_s": float(response.max()) if response.size else None,
            "commands_expected": expected,
            "commands_received": int(response.size),
            "commands_late": int(np.count_nonzero(response > period_s)),
            "missed_deadlines": dict(self.missed),
            "overruns": self.overruns,
            "agents": {rid: r.model_dump() for rid, r in self.inbox.reports.items()},
            "leadership": [a.model_dump() for a in self.inbox.leaders],
            "world_decode": self.stats.as_dict() if self.stats is not None else {},
            "log_overflow": self.inbox.overflow,
            **self._completeness(),
        }

    def _completeness(self) -> dict[str, object]:
        """Whether the run is whole: every tick run, no robot gone, every report in."""
        reasons = []
        if self.ticks_run < self.steps:
            reasons.append(f"the world ran {self.ticks_run} of {self.steps} ticks")
        reasons += [f"robot {r} was not there at the start" for r in self.absent]
        reasons += [f"robot {r} went away at tick {k}" for r, k in self.inbox.lost]
        missing = sorted(set(self.ids) - set(self.inbox.reports))
        if missing:
            reasons.append(f"no report from {', '.join(missing)}")
        return {
            "ticks_run": self.ticks_run,
            "lost": [{"robot": r, "tick": k} for r, k in self.inbox.lost],
            "absent": list(self.absent),
            "complete": not reasons,
            "incomplete_reason": "; ".join(reasons),
        }

    def _fill_states(self) -> None:
        root = self.formation.root
        for rid in self.ids:
            states, tr = self.inbox.states[rid], self.traces[rid]
            last = None
            for trace_list in (tr.states, tr.tracked, tr.leaders, tr.epochs, tr.formed):
                trace_list.clear()
            for k in range(self.steps):
                last = states.get(k, last)
                tr.states.append(last.fsm_state if last else str(State.HOLD))
                tr.direction[k] = last.direction if last else 1
                tr.tracked.append(last.leader_id if last else (self.formation.leader_of(rid) or ""))
                tr.leaders.append(last.formation_leader_id or root if last else root)
                tr.epochs.append(last.epoch if last else 0)
                tr.formed.append(last.formed if last else True)
                if last is not None:  # the pose it published (its estimate) and covariance
                    tr.estimate[k] = (last.x_m, last.y_m, last.theta_rad)
                    if last.cov:
                        tr.cov[k] = last.cov
