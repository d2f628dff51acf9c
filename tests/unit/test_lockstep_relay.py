"""The lockstep world's side of a tick: a robot's state is its answer (the world drives
the robot with the state's twist) and the next frames carry it to every other robot,
each state once; a robot that does not answer stands still for the tick. And who the
run starts with: a robot gone before it is marked absent, not forgotten."""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.runtime.world_process import WorldOptions, WorldProcess
from phalanx.wire.codec import DecodeStats
from phalanx.wire.keys import alive_key
from phalanx.wire.messages import Message, RobotState, SenseFrame, VelocityCommand
from phalanx.wire.transport import TransportConfig

FLEET = "relay"


@dataclass
class Recorder:
    """The session calls the world makes, its frames kept (no Zenoh: the world's own
    logic, which the process tests run over real sessions)."""

    stats: DecodeStats = field(default_factory=DecodeStats)
    frames: dict[str, list[SenseFrame]] = field(default_factory=dict)
    heard: list[type] = field(default_factory=list)  # the messages subscribed to

    def subscribe(self, key: str, model: type, handler: Callable[..., None], **_: Any) -> None:
        """Nothing arrives but what the test hands the world."""
        self.heard.append(model)

    def publish(self, key: str, message: Message, *, reliable_block: bool = False) -> None:
        if isinstance(message, SenseFrame):
            self.frames.setdefault(message.robot_id, []).append(message)

    def declare_alive(self, key: str) -> None:
        """Nothing to hold."""

    def watch_alive(self, key: str, on_change: Callable[[str, bool], None]) -> None:
        """Nobody comes or goes but what the test says."""

    def serve_status(self, key: str, status: Callable[[], dict[str, Any]]) -> None:
        """No queries."""


def _world() -> tuple[WorldProcess, Recorder]:
    scenario = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
    options = WorldOptions(
        fleet=FLEET, transport=TransportConfig(), tick_timeout_s=0.05, startup_timeout_s=0.3
    )
    world = WorldProcess(scenario, load_robot(scenario.robot), options)
    session = Recorder()
    world._wire(session)  # type: ignore[arg-type]
    for rid in world.ids:
        world._on_alive(alive_key(FLEET, rid), True)
    return world, session


def _answer(world: WorldProcess, rid: str, k: int) -> RobotState:
    state = RobotState(
        robot_id=rid, seq=k + 1, stamp_s=k * 0.1, x_m=0.0, y_m=0.0, theta_rad=0.0,
        v_mps=0.01 * (k + 1), omega_radps=0.001 * int(rid[1:]), fsm_state="FORMATION_TRACK",
    )  # fmt: skip
    world._on_state("", state)
    return state


def _relayed(session: Recorder, rid: str, k: int) -> dict[str, int]:
    """The tick of each state robot `rid`'s frame of tick `k` carried, by robot."""
    frame = session.frames[rid][k]
    assert frame.tick == k
    return {p.robot_id: round(p.stamp_s / frame.dt_s) for p in frame.peers}


def test_each_state_drives_its_robot_and_reaches_every_other_robot_once() -> None:
    world, session = _world()
    for k in range(2):
        for rid in world.ids:
            _answer(world, rid, k)
        world._tick(session, k)  # type: ignore[arg-type]
    _answer(world, "r1", 2)
    _answer(world, "r2", 2)
    world._tick(session, 2)  # type: ignore[arg-type]  # r3 is late for tick 2
    late = _answer(world, "r3", 2)
    for rid in world.ids:
        _answer(world, rid, 3)
    world._tick(session, 3)  # type: ignore[arg-type]
    world._tick(session, 4)  # type: ignore[arg-type]  # nobody answers tick 4

    assert _relayed(session, "r1", 0) == {}  # nothing heard before the first tick
    assert _relayed(session, "r1", 1) == {"r2": 0, "r3": 0}  # never its own
    assert _relayed(session, "r3", 1) == {"r1": 0, "r2": 0}
    assert _relayed(session, "r1", 2) == {"r2": 1, "r3": 1}
    assert _relayed(session, "r1", 3) == {"r2": 2, "r3": 2}  # r3's late one, now
    assert _relayed(session, "r1", 4) == {"r2": 3, "r3": 3}
    assert world.missed == {"r1": 1, "r2": 1, "r3": 2}  # r3 at tick 2; all at tick 4

    assert VelocityCommand not in session.heard  # a robot's state is its command
    trace = world.record.traces["r3"]
    assert trace.cmd_v_mps[1] == 0.02  # its state's twist
    assert trace.cmd_omega_radps[1] == 0.003
    assert trace.cmd_v_mps[2] == 0.0  # no answer in time: it stood still
    assert late.v_mps == 0.03  # (and its late answer was not taken for a later tick)
    assert trace.cmd_v_mps[3] == 0.04
    assert world.record.traces["r1"].cmd_v_mps[4] == 0.0


def test_a_robot_gone_before_the_start_is_absent_from_the_results_and_one_gone_after_lost() -> None:
    world, session = _world()
    world._on_alive(alive_key(FLEET, "r3"), False)  # killed while the fleet came up
    assert world.inbox.lost == []  # not yet a loss: it could come back before the start
    world._await_agents(threading.Event())  # waits out the startup timeout for it
    assert world.absent == ("r3",)
    world._tick(session, 0)  # type: ignore[arg-type]
    world._on_alive(alive_key(FLEET, "r2"), False)
    done = world._runtime()
    assert done["complete"] is False
    assert done["absent"] == ["r3"]
    assert done["lost"] == [{"robot": "r2", "tick": 0}]
    reason = str(done["incomplete_reason"])
    assert "robot r3 was not there at the start" in reason
    assert "robot r2 went away at tick 0" in reason


def test_a_robot_heard_after_its_liveliness_was_lost_is_waited_for_again() -> None:
    """Zenoh may not bring a token back after a lost link comes back: the robot's answers
    for the world's tick prove it is there; an old one does not."""
    world, session = _world()
    assert world.inbox.heard_s is None  # nothing heard yet: no silence is suspect
    for k in range(3):
        for rid in world.ids:
            _answer(world, rid, k)
        world._tick(session, k)  # type: ignore[arg-type]
    heard_s = world.inbox.heard_s  # what the world's Relinker watches
    assert heard_s is not None
    world._on_alive(alive_key(FLEET, "r2"), False)  # the world was frozen past the lease
    world._on_alive(alive_key(FLEET, "r3"), False)
    _answer(world, "r3", 0)  # a late one, from before
    assert world.inbox.alive == {"r1"}
    _answer(world, "r2", 2)  # its answer for the tick the world is at
    assert world.inbox.alive == {"r1", "r2"}
    assert world.inbox.heard_s is not None
    assert world.inbox.heard_s >= heard_s
    assert world.inbox.await_states(2, 0.01) == set()  # r2 is waited for again, r3 not
    assert world.inbox.await_states(3, 0.01) == {"r1", "r2"}
