"""Robots as separate processes over real Zenoh on loopback (scouting off)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from phalanx.analysis.metrics import run_metrics
from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_scenario
from phalanx.core.scenarios import signal_builder
from phalanx.runtime.batch import run_batch
from phalanx.wire.keys import leader_key, robot_key, robots_key
from phalanx.wire.messages import LeaderAnnouncement, RobotState
from phalanx.wire.transport import TransportConfig, free_tcp_port, loopback_endpoint, open_session

pytestmark = pytest.mark.integration
WEDGE = CONFIG_ROOT / "scenarios" / "paper_wedge.toml"
CLI = [sys.executable, "-m", "phalanx"]


def _stop(procs: list[subprocess.Popen[bytes]]) -> None:
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
    for proc in procs:
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


@pytest.fixture
def processes() -> Iterator[list[subprocess.Popen[bytes]]]:
    procs: list[subprocess.Popen[bytes]] = []
    yield procs
    _stop(procs)


def test_up_reproduces_the_in_process_run(
    tmp_path: Path, same_follower_metrics: Callable[..., None]
) -> None:
    """Lockstep over Zenoh gives the batch runner's metrics: both give every agent the
    peer states published one tick (100 ms) earlier, so they agree to rounding."""
    out = tmp_path / "up"
    proc = subprocess.run(
        [
            *CLI,
            "up",
            str(WEDGE),
            "--out",
            str(out),
            "--fleet",
            "same",
            "--timeout",
            "120",
            "--no-recording",
        ],
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    multi = json.loads((out / "metrics.json").read_text())
    single = run_metrics(run_batch(load_scenario(WEDGE)))
    same_follower_metrics(multi, single)
    assert [e["target"] for e in multi["transitions"]["r1"]] == [
        e["target"] for e in single["transitions"]["r1"]
    ]
    # One message out per robot and tick: its state, which the world drives it with (no
    # command sent); the other robots' states came in the frames, one tick old.
    runtime = multi["runtime"]
    assert "VelocityCommand" not in runtime["world_decode"]["ok"]
    assert runtime["world_decode"]["ok"]["RobotState"] == runtime["commands_expected"]
    assert runtime["commands_received"] == runtime["commands_expected"]
    assert not any(a["late_peer_steps"] for a in runtime["agents"].values())


def test_up_reproduces_a_leadership_handover(tmp_path: Path) -> None:
    """The leader alone blocked (its sonars read 0.3 m at 8 s): every robot process hands
    the lead to r2 under epoch 1 on the same tick as the in-process run, and the group's
    transitions and errors agree."""
    sets = ["duration_s=40", *signal_builder(8.0, robots=("r1",))]
    out = tmp_path / "handover"
    proc = subprocess.run(
        [*CLI, "up", str(WEDGE), "--out", str(out), "--fleet", "hand", "--timeout", "120",
         "--no-recording", *(a for s in sets for a in ("--set", s))],
        capture_output=True, text=True, timeout=180, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    multi = json.loads((out / "metrics.json").read_text())
    single = run_metrics(run_batch(apply_overrides(load_scenario(WEDGE), sets)))
    for rid in ("r1", "r2", "r3"):
        got = [(round(e["t_s"], 6), e["target"]) for e in multi["transitions"][rid]]
        want = [(round(e["t_s"], 6), e["target"]) for e in single["transitions"][rid]]
        assert got == want, rid
    assert "NAVIGATE" in [e["target"] for e in multi["transitions"]["r2"]]
    assert [a["leader_id"] for a in multi["runtime"]["leadership"]] == ["r2"]
    for rid in ("r1", "r3"):  # followers after the handover, errors against r2 and r1
        got = multi["followers"][rid]["forward"]["linear_pct"]["max"]
        want = single["followers"][rid]["forward"]["linear_pct"]["max"]
        assert got == pytest.approx(want, rel=1e-6, abs=1e-9), rid


def _spawn_fleet(
    fleet: str,
    endpoint: str,
    clock: str,
    duration_s: float,
    procs: list[subprocess.Popen[bytes]],
    out: Path,
    scenario: Path = WEDGE,
) -> None:
    """The world and r1-r3 as processes, each logging to `<out>/../logs/<name>.log`."""
    common = ["--fleet", fleet, "--clock", clock, "--set", f"duration_s={duration_s}"]
    world = ["world", str(scenario), *common, "--listen", endpoint, "--out", str(out),
             "--no-recording"]  # fmt: skip
    procs.append(_logged([*CLI, *world], _logs(out) / "world.log"))
    for rid in ("r1", "r2", "r3"):
        agent = ["agent", str(scenario), "--robot", rid, *common, "--mode", "client",
                 "--connect", endpoint]  # fmt: skip
        procs.append(_logged([*CLI, *agent], _logs(out) / f"{rid}.log"))


def _logs(out: Path) -> Path:
    """Where the processes of a fleet writing its results to `out` keep their logs."""
    logs = out.parent / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    return logs


def _logged(argv: list[str], log: Path) -> subprocess.Popen[bytes]:
    """`argv` started with its stderr (the log) appended to `log`."""
    with log.open("ab") as sink:
        return subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=sink)


def _tails(out: Path, lines: int = 15) -> str:
    """The last lines of every process's log, for a failure's message."""
    return "".join(
        f"\n--- {log.name}\n" + "\n".join(log.read_text(errors="replace").splitlines()[-lines:])
        for log in sorted(_logs(out).glob("*.log"))
    )


def _wait(predicate: object, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():  # type: ignore[operator]
            return True
        time.sleep(0.01)
    return False


def test_killed_leader_stops_the_followers_then_leadership_passes_and_it_rejoins(
    tmp_path: Path, processes: list[subprocess.Popen[bytes]]
) -> None:
    """The leader's process is killed: the followers stop within 500 ms, a new leader takes
    over under a higher epoch (announced on phalanx/<fleet>/leader), and the restarted
    robot rejoins as a follower, never taking the lead back."""
    endpoint, out = loopback_endpoint(free_tcp_port()), tmp_path / "out"
    _spawn_fleet("kill", endpoint, "realtime", 60.0, processes, out)
    seen: dict[str, tuple[float, RobotState]] = {}
    announced: list[LeaderAnnouncement] = []
    lock = threading.Lock()

    def record(_key: str, state: RobotState) -> None:
        with lock:
            seen[state.robot_id] = (time.monotonic(), state)

    def latest(rid: str) -> tuple[float, RobotState]:
        with lock:
            return seen[rid]

    with open_session(TransportConfig(mode="client", connect=(endpoint,))) as session:
        session.subscribe(robots_key("kill", "state"), RobotState, record)
        session.subscribe(leader_key("kill"), LeaderAnnouncement, lambda _k, a: announced.append(a))
        tracking = _wait(
            lambda: all(
                rid in seen
                and seen[rid][1].fsm_state == "FORMATION_TRACK"
                and seen[rid][1].stamp_s > 3
                for rid in ("r2", "r3")
            ),
            40.0,
        )
        assert tracking, f"followers never tracked: {seen}{_tails(out)}"
        leader = processes[1]
        leader.send_signal(signal.SIGKILL)
        killed_at = time.monotonic()
        leader.wait(5)

        def stopped() -> bool:
            return all(
                latest(r)[1].fsm_state == "HOLD" and latest(r)[0] > killed_at for r in ("r2", "r3")
            )

        assert _wait(stopped, 2.0), f"followers did not stop: {seen}{_tails(out)}"
        noticed_s = max(latest(r)[0] for r in ("r2", "r3")) - killed_at
        assert noticed_s < 0.5, f"followers stopped {noticed_s:.3f} s after the kill"

        # The rule elects the best live robot (r2: clear, most forward, first) under epoch 1.
        def new_leader() -> bool:
            r2, r3 = latest("r2")[1], latest("r3")[1]
            return (
                r2.fsm_state == "NAVIGATE"
                and r2.leader_id == ""
                and r2.epoch == 1
                and r3.formation_leader_id == "r2"
                and r3.epoch == 1
                and r3.leader_id == "r2"
                and r3.fsm_state == "FORMATION_TRACK"
            )

        assert _wait(new_leader, 10.0), f"no new leader: {seen}{_tails(out)}"
        assert [(a.leader_id, a.epoch, a.previous_id) for a in announced] == [("r2", 1, "r1")]

        # The old leader's process is started again: it joins as a follower of the
        # fleet's leader. Until it drives off, its robot stands where it stopped, at the
        # front of the wedge: a leader it blocks for 2 s hands over to a clear robot
        # (announced, under the next epoch), which a busy machine's slow start gives time.
        processes.append(_logged(list(leader.args), _logs(out) / "r1-again.log"))
        restarted_at = time.monotonic()

        def rejoined() -> bool:
            with lock:
                if "r1" not in seen or seen["r1"][0] <= restarted_at:
                    return False
                r1 = seen["r1"][1]
            r2, r3 = latest("r2")[1], latest("r3")[1]
            head = r3.formation_leader_id
            return (
                r1.fsm_state == "FORMATION_TRACK"
                and r1.epoch == r2.epoch == r3.epoch == len(announced)
                and r1.formation_leader_id == r2.formation_leader_id == head
                and head in ("r2", "r3")
                and r1.leader_id != ""
            )

        assert _wait(rejoined, 30.0), (
            f"r1 did not rejoin as a follower: {seen}, announced {announced}{_tails(out)}"
        )
        # rejoining flipped nothing back: every later handover went to another robot,
        # announced by it under the next epoch
        assert all(a.leader_id != "r1" for a in announced), announced
        assert [a.epoch for a in announced] == list(range(1, len(announced) + 1)), announced


def test_malformed_payloads_on_every_key_are_counted_and_ignored(
    tmp_path: Path, processes: list[subprocess.Popen[bytes]]
) -> None:
    endpoint = loopback_endpoint(free_tcp_port())
    out = tmp_path / "out"
    _spawn_fleet("junk", endpoint, "realtime", 20.0, processes, out)
    with open_session(TransportConfig(mode="client", connect=(endpoint,))) as session:
        assert _wait(lambda: len(session.query_status("phalanx/junk/status/*", 1.0)) >= 4, 40.0)
        garbage = [
            b"",
            b"\x00",
            b"\x01\x01\xff",
            b"{not json",
            b'{"version": 99}',
            bytes(range(256)),
        ]
        for rid in ("r1", "r2", "r3"):
            for topic in ("state", "flags", "sense", "cmd", "event", "report"):
                for payload in garbage:
                    session.publish_raw(robot_key("junk", rid, topic), payload)
        time.sleep(1.0)
        statuses = session.query_status("phalanx/junk/status/*", 2.0)
    processes[0].wait(60)  # the world finishes its 20 s and writes results
    assert processes[0].returncode == 0
    assert (out / "metrics.json").exists()
    agents = [s for s in statuses if "robot_id" in s]
    assert len(agents) == 3
    for status in agents:
        decode = status["decode"]
        assert isinstance(decode, dict)
        assert sum(decode["malformed"].values()) + sum(decode["unknown_version"].values()) >= len(
            garbage
        )


def test_every_robots_sonar_scans_reach_every_other_robots_map(
    tmp_path: Path, processes: list[subprocess.Popen[bytes]]
) -> None:
    endpoint = loopback_endpoint(free_tcp_port())
    nav = CONFIG_ROOT / "scenarios" / "nav_corridor_wedge3.toml"
    _spawn_fleet("maps", endpoint, "realtime", 15.0, processes, tmp_path / "out", nav)
    heard: dict[str, int] = {}
    left_out: dict[str, object] = {}  # echoes each map took for another robot of the fleet
    with open_session(TransportConfig(mode="client", connect=(endpoint,))) as session:

        def everyone_heard_the_others() -> bool:
            for status in session.query_status("phalanx/maps/status/*", 1.0):
                if "scans_heard" in status:
                    heard[str(status["robot_id"])] = int(status["scans_heard"])
                    left_out[str(status["robot_id"])] = status.get("robot_echoes_left_out")
            return len(heard) == 3 and min(heard.values()) >= 20

        assert _wait(everyone_heard_the_others, 40.0), heard
    assert all(isinstance(n, int) and n >= 0 for n in left_out.values()), left_out
    processes[0].wait(60)
    assert processes[0].returncode == 0


def test_an_agent_whose_world_is_gone_exits_with_its_own_code(
    processes: list[subprocess.Popen[bytes]],
) -> None:
    """No frame from the world for --frame-timeout: the agent stops its robot and exits 3,
    not 0, so a host daemon restarts it to rejoin rather than taking the run as done."""
    endpoint = loopback_endpoint(free_tcp_port())
    argv = [*CLI, "agent", str(WEDGE), "--robot", "r2", "--fleet", "lost", "--mode", "peer",
            "--listen", endpoint, "--frame-timeout", "1.5"]  # fmt: skip
    started = time.monotonic()
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    processes.append(proc)
    _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 3, err.decode()[-2000:]
    assert b"no frame from the world for 1.5 s" in err
    assert time.monotonic() - started < 30.0
