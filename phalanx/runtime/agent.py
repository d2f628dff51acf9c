"""The agent process: one runtime, built from a clock and a robot I/O.

A simulated robot steps on the world's sense frames and sends its commands back to the
world (`WorldLink`, which is both its clock and its I/O); a robot on a driver steps on
its own clock (`EpochClock`) and commands its robot through the safety wrapper
(`DriverIO`). Either way a step is the same: what the robot senses and what the fleet
said, the agent's step, the command out, the state, flags, transitions and leadership
published, telemetry logged. A robot started while its fleet is already running (its
first tick is not 0) joins: it stays still until it has heard the fleet's leader and
epoch. What an operator asks of the robot (`phalanx.runtime.operator`) goes into its
observation.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from phalanx.agents.agent import Agent, Observation, StepOutput
from phalanx.agents.navigation import warm_kernels
from phalanx.agents.perception import SonarGeometry
from phalanx.core import compiled
from phalanx.core.config import Scenario
from phalanx.core.formation import Formation, scenario_formation
from phalanx.core.peers import PeerState
from phalanx.core.rigid_body import live_errors
from phalanx.core.robot_params import RobotParams
from phalanx.runtime.clock import Clock, Tick
from phalanx.runtime.heap import lifelong_heap
from phalanx.runtime.operator import OperatorInbox
from phalanx.runtime.peers import FlagsThrottle, PeerInbox, ScanInbox
from phalanx.runtime.robot_io import RobotIO
from phalanx.runtime.signals import Stoppable
from phalanx.telemetry.stream import Telemetry
from phalanx.wire.bounds import MAX_TEXT, UINT32_MAX, FleetBounds
from phalanx.wire.keys import alive_key, alive_pattern, leader_key, robot_key, status_key
from phalanx.wire.messages import (
    AgentEvent,
    AgentReport,
    LeaderAnnouncement,
    Message,
    RobotFlags,
    RobotState,
    ScanMessage,
)
from phalanx.wire.relink import Relinker
from phalanx.wire.transport import FleetSession, TransportConfig, open_session

log = logging.getLogger("phalanx.agent")
ClockMode = Literal["lockstep", "realtime"]
# Unchanged flags go out at least this often (and three times per leader timeout).
FLAGS_HEARTBEAT_S = 0.2
REPORT_FLUSH_S = 2.0  # how long the final report waits for telemetry to go out


@dataclass
class RuntimeOptions:
    """How an agent process runs."""

    fleet: str
    transport: TransportConfig
    clock: ClockMode = "lockstep"


class AgentRuntime:
    """One robot's process loop around an `Agent`, on `clock`, reaching its robot by `io`."""

    def __init__(
        self,
        robot_id: str,
        scenario: Scenario,
        robot: RobotParams,
        options: RuntimeOptions,
        *,
        clock: Clock,
        io: RobotIO,
        telemetry: Telemetry | None = None,
    ) -> None:
        self.robot_id = robot_id
        self.scenario, self.robot, self.options = scenario, robot, options
        self.clock, self.io, self.telemetry = clock, io, telemetry
        self.formation: Formation = scenario_formation(scenario)
        self.bounds = FleetBounds.of(scenario, robot)
        self.agent = Agent(robot_id, scenario=scenario, robot=robot, formation=self.formation)
        compiled.choice()  # (a PHALANX_KERNELS it does not know stops it before it starts)
        if scenario.navigation.reactive:  # (numba's, if asked for: loaded now, not mid-run)
            warm_kernels(SonarGeometry.from_params(robot))
        self.inbox = PeerInbox(
            robot_id, self.formation, fleet=options.fleet, lockstep=self.lockstep,
            bounds=self.bounds,
        )  # fmt: skip
        self.scans = ScanInbox(robot_id, self.formation, fleet=options.fleet)
        self.operator = OperatorInbox(options.fleet, robot_id)
        self._scan_sent_s = -1.0
        self.flags_out = FlagsThrottle(min(FLAGS_HEARTBEAT_S, scenario.leader_timeout_s / 3))
        self.step_times_s: list[float] = []
        self.steps = 0
        self.unsent = 0  # own messages that could not be encoded or sent (logged)
        self.stale_steps = 0  # real-time steps too late to send (a frozen process)
        self.last: StepOutput | None = None
        self._paths: dict[str, tuple[str, ...]] = {}  # follow-tree path to each leader
        self._session: FleetSession | None = None

    @property
    def lockstep(self) -> bool:
        """Whether the fleet runs in lockstep (deterministic, one machine)."""
        return self.options.clock == "lockstep"

    @property
    def watched(self) -> tuple[str, ...]:
        """Robots whose full state this one needs: everyone in lockstep; else those on
        its follow-tree path to the leader (any of them may become the one it tracks).
        """
        if self.lockstep or self.scenario.localisation.markers is not None:
            # (relative measurements may be of any robot before this one: hear them all)
            return tuple(r for r in self.formation.robot_ids if r != self.robot_id)
        leader = self.formation.root if self.last is None else self.last.state.formation_leader_id
        if leader == self.robot_id:
            return ()
        if leader not in self._paths:
            self._paths[leader] = self.formation.tree_path(self.robot_id, leader)
        return self._paths[leader]

    def run(self, stop: Stoppable) -> AgentReport:
        """Step until the clock runs out (the world's final frame, the scenario's end),
        `stop`, or the robot's side goes quiet; then report.
        """
        fleet = self.options.fleet
        with (
            open_session(self.options.transport) as session,
            Relinker(session, self._heard) as relinker,
        ):
            self._session = session
            self._wire(session)
            relinker.start()
            try:
                with lifelong_heap():
                    while (tick := self.clock.next_tick(stop)) is not None:
                        observation = self.io.read(tick)
                        if observation is not None:
                            self.step(tick, observation)
            finally:
                self.io.halt()
            report = self._report()
            self._send(robot_key(fleet, self.robot_id, "report"), lambda: report, block=True)
            time.sleep(0.05)  # let the last puts leave before the session closes
        return report

    def _wire(self, session: FleetSession) -> None:
        fleet, rid = self.options.fleet, self.robot_id
        session.declare_alive(alive_key(fleet, rid))
        self.io.attach(session)
        self.inbox.attach(session, self.watched)
        self.scans.attach(session, self.bounds)
        self.operator.attach(session, self.bounds)
        session.watch_alive(alive_pattern(fleet), self._on_alive)
        session.serve_status(status_key(fleet, rid), self._status)

    def _heard(self) -> float | None:
        """When this process last heard what it expects from the fleet: the world's
        frames, another robot's flags or state (None: nothing yet, or a fleet of one).
        """
        heard = [t for t in (self.io.heard_s(), self.inbox.heard_s) if t is not None]
        return max(heard, default=None)

    def _on_alive(self, key: str, alive: bool) -> None:
        self.inbox.on_alive(key.rsplit("/", 1)[-1], alive)

    def _status(self) -> dict[str, object]:
        stats = self._session.stats.as_dict() if self._session else {}
        state = self.last.state if self.last is not None else None
        estimator = self.agent.estimator  # (its measurements' outcomes: fused, gated, ...)
        return {
            "robot_id": self.robot_id,
            "steps": self.steps,
            "state": state.fsm_state if state else self.agent.state_name,
            "leader": state.formation_leader_id if state else self.formation.root,
            "epoch": state.epoch if state else 0,
            "leader_claims_refused": self.agent.leadership.refused,
            "late_peer_steps": self.inbox.late_steps,
            "scans_heard": self.scans.heard,
            "robot_echoes_left_out": self.agent.robot_echoes_left_out,
            "estimator": dict(estimator.stats.counts) if estimator is not None else {},
            **self.operator.counters(),
            "flags_skipped": self.flags_out.skipped,
            "unsent": self.unsent,
            "stale_steps": self.stale_steps,
            "dropped": self._session.stats.dropped if self._session else 0,
            "relinks": self._session.relinks if self._session else 0,
            "decode": stats,
            **self.io.counters(),
        }

    def step(self, tick: Tick, observation: Observation) -> StepOutput:
        """One control step: the agent's step, the command out, everything published."""
        if self.steps == 0 and tick.k > 0:
            # The fleet started without this process (a restart): join, do not lead.
            self.agent = Agent(
                self.robot_id,
                scenario=self.scenario,
                robot=self.robot,
                formation=self.formation,
                joining=True,
            )
        began = time.monotonic()
        self.inbox.drain()
        self.inbox.relayed(self.io.relayed())
        delay_s = max(self.scenario.comm_delay_s, self.scenario.dt_s)
        peers, flags = self.inbox.for_step(tick.t_s, delay_s=delay_s, watched=self.watched)
        heard = self.scans.take()
        if heard:
            observation = dataclasses.replace(observation, scans=observation.scans + heard)
        operator = self.operator.take(tick.t_s)
        if operator is not None:
            observation = dataclasses.replace(observation, operator=operator)
        started = time.perf_counter()
        out = self.agent.step(observation, peers, tick.t_s, None if self.lockstep else flags)
        self._count_refusals()
        if self._stale(began, tick):
            self.inbox.keep_own(out.state, out.flags)
        else:
            if not self.lockstep:  # (in lockstep the state carries the command: one put)
                self.io.write(tick, out.command)
            # Asked again: a process frozen while its command went out must not resume
            # by publishing the state it had before (a peer would take it as news).
            if self._stale(began, tick):
                self.inbox.keep_own(out.state, out.flags)
            else:
                self._publish(out)
        if self.telemetry is not None:
            self._log_step(tick, observation, out, peers)
        self.last = out
        self.steps += 1
        self.step_times_s.append(time.perf_counter() - started)
        if not self.lockstep:
            self.inbox.follow(self.watched)  # the leader may have changed: hear the new path
        return out

    def _count_refusals(self) -> None:
        """Count the peers' leadership claims the agent refused where a user looks (the
        session's `rejected` counters, under the message that carried them), and log them.
        """
        refusals = self.agent.leadership.refusals
        kind = "RobotState" if self.lockstep else "RobotFlags"
        while refusals:
            claim = refusals.popleft()
            text = f"{kind} of {claim.robot_id}: {claim.describe()}"
            if self._session is not None:
                self._session.stats.count("rejected", kind, text)
            refused = self.agent.leadership.refused
            if refused <= 10 or refused % 1000 == 0:
                log.warning("%s: leadership claim refused (%d so far): %s", self.robot_id,
                            refused, text)  # fmt: skip

    def _stale(self, began: float, tick: Tick) -> bool:
        """Whether this real-time step took so long (the process was frozen, or starved)
        that its command and state are stale: older than a peer would accept. Such a step
        is not sent (a leader resumed after a freeze would claim the lead with old news);
        the next step, on the newest frame, is.
        """
        limit_s = self.scenario.leader_timeout_s
        took_s = time.monotonic() - began
        if self.lockstep or (took_s <= limit_s and self.io.lag_s(tick) <= limit_s):
            return False
        self.stale_steps += 1
        log.warning("%s: step %d is over %.1f s late: not sent", self.robot_id, tick.k, limit_s)
        return True

    def _send(self, key: str, build: Callable[[], Message], *, block: bool = False) -> None:
        """Publish what `build` makes; a message that cannot be built or sent (a value
        out of the wire's bounds) is logged and counted, never let end the process.
        """
        assert self._session is not None  # noqa: S101 - only called inside run()
        try:
            self._session.publish(key, build(), reliable_block=block)
        except Exception as exc:  # the command already went out; the state must not stop it
            self.unsent += 1
            if self.unsent <= 10 or self.unsent % 1000 == 0:
                log.error("%s: could not send %s (%d so far): %s", self.robot_id, key,
                          self.unsent, exc)  # fmt: skip

    def _publish(self, out: StepOutput) -> None:
        fleet, rid = self.options.fleet, self.robot_id
        # In lockstep the state is the robot's answer to the world's frame, which the world
        # waits for and relays to the others: it must arrive, as the command does (DROP
        # gives up on a message the link's queue has had no room for within a millisecond).
        state_key = robot_key(fleet, rid, "state")
        self._send(state_key, lambda: RobotState.of(out.state), block=self.lockstep)
        flags = out.flags
        if not self.lockstep and self.flags_out.due(flags):  # (lockstep: the states do)
            self._send(robot_key(fleet, rid, "flags"), lambda: RobotFlags.of(flags))
        self.inbox.keep_own(out.state, flags)
        scan = out.scan
        if scan is not None and scan.stamp_s > self._scan_sent_s:  # each reading once
            self._scan_sent_s = scan.stamp_s
            self._send(robot_key(fleet, rid, "scan"), lambda: ScanMessage.of(scan))
        change = out.leadership
        if change is not None:
            self._send(
                leader_key(fleet),
                lambda: LeaderAnnouncement(
                    leader_id=change.leader_id, epoch=change.epoch, stamp_s=change.t_s,
                    previous_id=change.previous_id, reason=change.reason[:MAX_TEXT],
                ),
                block=True,
            )  # fmt: skip
        for event in out.events:
            self._send(
                robot_key(fleet, rid, "event"),
                lambda event=event: AgentEvent(  # type: ignore[misc]
                    robot_id=rid, t_s=event.t_s, source=event.source, target=event.target,
                    reason=event.reason[:MAX_TEXT],
                ),
                block=True,
            )  # fmt: skip

    def _log_step(
        self, tick: Tick, observation: Observation, out: StepOutput, peers: dict[str, PeerState]
    ) -> None:
        telemetry = self.telemetry
        assert telemetry is not None  # noqa: S101 - checked by the caller
        state = out.state
        if self.steps == 0:  # the state log starts with the state the robot starts in
            telemetry.log_transition(
                self.robot_id, t_s=tick.t_s, source="-", target=state.fsm_state,
                reason="agent started",
            )  # fmt: skip
        for event in out.events:
            telemetry.log_transition(
                self.robot_id, t_s=event.t_s, source=event.source, target=event.target,
                reason=event.reason,
            )  # fmt: skip
        leader = peers.get(state.leader_id) if state.leader_id else None
        tracking = None
        if leader is not None:  # computed on the telemetry thread, off the control step
            tracking = functools.partial(
                live_errors, self.formation, self.robot_id, state.pose, leader, t_s=tick.t_s
            )
        telemetry.log_step(
            self.robot_id,
            t_s=tick.t_s,
            step=tick.k,
            pose=state.pose,
            cmd=out.command,
            measured=observation.odometry.twist,
            tracking=tracking,
            sonar=self.robot.sonar,
            sonar_ranges_m=observation.status.sonar_ranges_m,
            fsm_state=state.fsm_state,
            leader_id=state.leader_id,
            cov=state.cov,
        )

    def _report(self) -> AgentReport:
        dropped = self._session.stats.dropped if self._session else 0
        times = sorted(self.step_times_s) or [0.0]
        if self.telemetry is not None:  # the count is final once the last rows went out
            self.telemetry.flush(REPORT_FLUSH_S)
        last = self.last
        return AgentReport(
            robot_id=self.robot_id,
            steps=self.steps,
            saturations=last.saturations if last else 0,
            accel_limited=last.accel_limited if last else 0,
            dropped_messages=min(dropped, UINT32_MAX),
            late_peer_steps=self.inbox.late_steps,
            step_p50_us=1e6 * times[len(times) // 2],
            step_p99_us=1e6 * times[min(len(times) - 1, round(0.99 * (len(times) - 1)))],
            telemetry_dropped=self.telemetry.dropped if self.telemetry else 0,
            commands_sent=min(self.io.counters().get("commands_sent", 0), UINT32_MAX),
        )
