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

Robots that move on their own (`WorldOptions.observed`: robots on real drivers, or in
another simulator such as AMRISim) are not simulated: the world places them where the
best source it hears says they are (`phalanx.runtime.observed`), sends them no frames,
and records them from that source; the results name it per robot.

Checkpoints: every `checkpoint_every_s` of wall time (longer if a checkpoint costs more
than CHECKPOINT_SHARE of the time between them) the world hands the log of the ticks run
so far to its `checkpoint` on a thread of its own (the CLI writes `metrics.json` and
`traces.npz` from it, marked incomplete; a tick is never late for it), so that a world
killed mid-run leaves the errors up to then. A checkpoint that fails (a full disk) is
logged once and tried again at the next one; the run goes on.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from phalanx.core.config import Scenario
from phalanx.core.errors import ConfigError
from phalanx.core.formation import scenario_formation
from phalanx.core.geometry import ZERO_TWIST, Twist2D
from phalanx.core.limits import KinematicLimits
from phalanx.core.robot_params import RobotParams
from phalanx.core.runlog import RunLog
from phalanx.runtime.clock import WorldSchedule
from phalanx.runtime.heap import lifelong_heap
from phalanx.runtime.observed import observed_robots
from phalanx.runtime.run_record import RunRecord, completeness, done_when_it_left
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
# A checkpoint takes at most this share of the world's wall time (a fleet whose record
# costs more to compute is checkpointed less often).
CHECKPOINT_SHARE = 0.02
CHECKPOINT_JOIN_S = 60.0


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
    observed: tuple[str, ...] = ()  # robots that move on their own: recorded, not simulated
    checkpoint_every_s: float = 2.0  # wall time between checkpoints (at the least)


class WorldProcess:
    """Simulates the scenario's world for agents in other processes."""

    def __init__(
        self,
        scenario: Scenario,
        robot: RobotParams,
        options: WorldOptions,
        *,
        telemetry: Telemetry | None = None,
        checkpoint: Callable[[RunLog], None] | None = None,
    ) -> None:
        self.scenario, self.robot, self.options = scenario, robot, options
        self.telemetry = telemetry
        self.checkpoint = checkpoint  # takes the log so far; may raise OSError
        self.checkpoints = 0  # written
        self.checkpoint_failures = 0
        self._checkpoint_failing = False
        self._next_checkpoint = 0.0  # (monotonic)
        self._checkpointer: threading.Thread | None = None
        self.world = World.for_scenario(scenario, robot)
        self.formation = scenario_formation(scenario)
        self.bounds = FleetBounds.of(scenario, robot)
        self.ids = tuple(r.id for r in scenario.robots)
        self.record = RunRecord(scenario, self.formation, self.ids)
        self.steps = self.record.steps
        self.inbox = WorldInbox(self.ids)
        self.missed: dict[str, int] = dict.fromkeys(self.ids, 0)
        self.tick = 0
        self.ticks_run = 0
        self.started = False  # past the start, a robot that goes away is lost to the run
        self.absent: tuple[str, ...] = ()  # robots not there when the run started
        self._fabric: FleetSession | None = None  # the session, once open
        self.wall_time_s = 0.0
        self.schedule = WorldSchedule(scenario.dt_s / options.speed, options.epoch_s)
        self._ahead_ticks = max(2, round(AHEAD_S / scenario.dt_s))
        if options.clock == "lockstep" and options.transport.lowlatency:
            self._check_frames_fit()
        self.observed = observed_robots(
            options.observed, self.ids, fleet=options.fleet, clock=options.clock,
            epoch_s=options.epoch_s, bounds=self.bounds,
        )  # fmt: skip
        self.observed_ids = frozenset(self.observed.ids if self.observed else ())
        self._observed_twist: dict[str, Twist2D] = {}

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
            epoch = self.options.epoch_s
            if self.options.clock == "realtime" and epoch is not None:
                stop.wait(max(0.0, epoch - time.time()))
            started = time.perf_counter()
            self._next_checkpoint = time.monotonic() + self.options.checkpoint_every_s
            self.schedule.start()
            with lifelong_heap():
                for k in range(self.steps):
                    if stop.is_set():
                        break
                    self._tick(session, k)
                    self._maybe_checkpoint(started)
                    if self.options.clock == "realtime":
                        time.sleep(self.schedule.wait_s())
            self.wall_time_s = time.perf_counter() - started
            self._last_checkpoint_done()
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
        # In real time a robot's state and command come once a period: a flood beyond a few
        # times that is dropped and counted (in lockstep the world sets the pace itself).
        realtime = self.options.clock == "realtime"
        periodic = self.options.speed / self.scenario.dt_s if realtime else None
        subscriptions = [
            (robots_key(fleet, "state"), RobotState, self._on_state, periodic),
            (robots_key(fleet, "event"), AgentEvent, self._on_event, None),
            (robots_key(fleet, "report"), AgentReport, self._on_report, None),
            (leader_key(fleet), LeaderAnnouncement, self._on_leader, None),
        ]
        if realtime:  # (in lockstep a robot's state is its command)
            subscriptions.append(
                (robots_key(fleet, "cmd"), VelocityCommand, self._on_command, periodic)
            )
        for key, model, handler, rate_hz in subscriptions:
            session.subscribe(key, model, handler, context=bounds, rate_hz=rate_hz)  # type: ignore[arg-type]
        session.watch_alive(alive_pattern(fleet), self._on_alive)
        session.serve_status(status_key(fleet, WORLD_ID), self._status)
        if self.observed is not None:
            self.observed.attach(session)

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
            why = self.inbox.leaders.propose(announcement, time.monotonic())
        if why and self.stats is not None:
            self.stats.count("rejected", "LeaderAnnouncement", f"LeaderAnnouncement: {why}")

    def _on_report(self, _key: str, report: AgentReport) -> None:
        with self.inbox.cond:
            self.inbox.reports[report.robot_id] = report
            self.inbox.cond.notify_all()

    def _on_alive(self, key: str, alive: bool) -> None:
        robot = key.rsplit("/", 1)[-1]
        if robot not in self.inbox.ids:
            return  # another process (a tool, the world itself) or no robot of this fleet
        with self.inbox.cond:
            (self.inbox.alive.add if alive else self.inbox.alive.discard)(robot)
            tick = self._run_tick() if self.started and not alive else None
            if not alive:
                self.inbox.gone(robot, tick)
            done = tick is not None and done_when_it_left(
                robot, tick, self.inbox.reports, self.steps
            )
            self.inbox.cond.notify_all()
        if alive:
            return
        if done:
            log.info("robot %s has left, its run done", robot)
        else:
            log.warning("robot %s is gone (liveliness lost)", robot)

    def _run_tick(self) -> int:
        """The run's tick now: on the shared epoch's clock where there is one (a world
        late on a loaded machine is behind it; a robot on its own clock is not), else
        the world's own.
        """
        epoch = self.options.epoch_s
        if epoch is None or self.options.clock != "realtime":
            return self.tick
        speed, dt_s = self.options.speed, self.scenario.dt_s
        return max(self.tick, min(self.steps - 1, int((time.time() - epoch) * speed / dt_s)))

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
            **(self.observed.counters() if self.observed is not None else {}),
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
        self._place_observed(k)
        self.world.sense_all()  # every robot's sonar in one pass; each frame reads its row
        lockstep = self.options.clock == "lockstep"
        # (a state older than the window kept ahead is no news either)
        relay = self.inbox.relay(k, self._ahead_ticks) if lockstep else ()
        for rid in self.ids:
            if rid in self.observed_ids:
                # no frame: it senses for itself; its simulated positioning (motion
                # capture, cameras) only once its true pose is known, which it measures
                if self.observed is not None and self.observed.has_truth(rid):
                    self._positioning(session, rid)
                continue
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
        self.record.record(k, self.world, commands, self.telemetry)
        self.world.step(commands, self.scenario.dt_s)

    def _place_observed(self, k: int) -> None:
        """Put every observed robot where it is at tick `k`, moving as it does."""
        if self.observed is None:
            return
        t_s = float(self.record.t_s[k])
        for rid in self.observed.ids:
            seen = self.observed.at(rid, t_s)
            if seen is not None:
                pose, twist = seen
                self.world.place(rid, pose, twist)
                self._observed_twist[rid] = twist

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
        # (an observed robot goes on as it was seen going; in the record, its command is
        # its own: it sends none to the world)
        return out | self._observed_twist

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

    def _finish(self, session: FleetSession) -> None:
        """The final frame, again to robots whose report is not in (`await_reports`)."""
        fleet, k, dt_s = self.options.fleet, self.tick, self.scenario.dt_s
        self.inbox.await_reports(
            lambda robots: send_final(session, self.world, fleet, robots, k, dt_s),
            timeout_s=self.options.report_timeout_s, every_s=FINAL_RESEND_S, grace_s=REPORT_GRACE_S,
        )  # fmt: skip

    def _maybe_checkpoint(self, started: float) -> None:
        """Hand the log so far to `checkpoint` if one is due (see the module's docstring):
        copied here, written on a thread of its own so that a tick is never late for it.
        """
        busy = self._checkpointer is not None and self._checkpointer.is_alive()
        if self.checkpoint is None or busy or time.monotonic() < self._next_checkpoint:
            return
        if self.ticks_run < 1:
            return
        so_far = self._log_so_far(time.perf_counter() - started)
        self._checkpointer = threading.Thread(
            target=self._write_checkpoint, args=(self.checkpoint, so_far, self.tick),
            name="checkpoint", daemon=True,
        )  # fmt: skip
        self._checkpointer.start()

    def _write_checkpoint(self, write: Callable[[RunLog], None], so_far: RunLog, tick: int) -> None:
        began = time.monotonic()
        try:
            write(so_far)
        except OSError as exc:
            self.checkpoint_failures += 1
            if not self._checkpoint_failing:  # (once, until one is written again)
                log.error("checkpoint at tick %d not written (the run goes on): %s", tick, exc)
            self._checkpoint_failing = True
        except Exception as exc:  # a checkpoint's bug must not end the run it records
            self.checkpoint_failures += 1
            log.error("checkpoint at tick %d failed (the run goes on): %r", tick, exc)
        else:
            if self._checkpoint_failing:
                log.info("checkpoint written again at tick %d", tick)
            self.checkpoints += 1
            self._checkpoint_failing = False
        cost_s = time.monotonic() - began
        every_s = max(self.options.checkpoint_every_s, cost_s / CHECKPOINT_SHARE)
        self._next_checkpoint = time.monotonic() + every_s

    def _last_checkpoint_done(self) -> None:
        """Wait (bounded) for a checkpoint still being written: the final results follow."""
        if self._checkpointer is not None:
            self._checkpointer.join(CHECKPOINT_JOIN_S)
            if self._checkpointer.is_alive():
                log.error("a checkpoint still writing after %.0f s", CHECKPOINT_JOIN_S)

    def _log_so_far(self, wall_time_s: float) -> RunLog:
        """The log of the ticks run so far, from copies (the Zenoh threads go on filing)."""
        with self.inbox.cond:
            states = {rid: dict(got) for rid, got in self.inbox.states.items()}
            events, reports = list(self.inbox.events), dict(self.inbox.reports)
            runtime = self._runtime()
        return self.record.head(self.ticks_run).log(
            self.robot,
            states=states,
            events=events,
            reports=reports,
            observed=self.observed,
            world=self.world,
            runtime=runtime,
            wall_time_s=wall_time_s,
        )

    def _log(self) -> RunLog:
        return self.record.log(
            self.robot,
            states=self.inbox.states,
            events=self.inbox.events,
            reports=self.inbox.reports,
            observed=self.observed,
            world=self.world,
            runtime=self._runtime(),
            wall_time_s=self.wall_time_s,
        )

    def _runtime(self) -> dict[str, object]:
        """Figures of the run as processes: response times, deadlines, reports."""
        period_s = self.scenario.dt_s / self.options.speed
        response = np.asarray(self.inbox.response_s, dtype=np.float64)
        quantiles: list[float | None] = (
            np.quantile(response, [0.5, 0.99]).tolist() if response.size else [None, None]
        )
        expected = (self.tick + 1) * len(self.ids)
        # (an observed robot's commands go to its driver: its agent's report counts them)
        delivered = sum(r.commands_sent for rid, r in self.inbox.reports.items()
                        if rid in self.observed_ids)  # fmt: skip
        return {
            "clock": self.options.clock,
            "period_s": period_s,
            "response_p50_s": quantiles[0],
            "response_p99_s": quantiles[1],
            "response_max_s": float(response.max()) if response.size else None,
            "commands_expected": expected,
            "commands_received": int(response.size) + delivered,
            "commands_late": int(np.count_nonzero(response > period_s)),
            "missed_deadlines": dict(self.missed),
            "overruns": self.schedule.overruns,
            "agents": {rid: r.model_dump() for rid, r in self.inbox.reports.items()},
            "leadership": [a.model_dump() for a in self.inbox.leaders.settle()],
            "leadership_refused": self.inbox.leaders.refused,
            "world_decode": self.stats.as_dict() if self.stats is not None else {},
            "log_overflow": self.inbox.overflow,
            **(self.observed.counters() if self.observed is not None else {}),
            **completeness(
                steps=self.steps,
                ticks_run=self.ticks_run,
                absent=self.absent,
                lost=self.inbox.lost,
                reports=self.inbox.reports,
                ids=self.ids,
            ),
        }
