"""Robots as separate processes over real Zenoh on loopback (scouting off)."""

from __future__ import annotations

import json
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fleetlab import CLI, ROBOTS, WEDGE, Seen, running_fleet, terminate, wait_for

from phalanx.analysis.metrics import run_metrics
from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_scenario
from phalanx.core.scenarios import signal_builder
from phalanx.runtime.batch import run_batch
from phalanx.wire.keys import robot_key
from phalanx.wire.transport import free_tcp_port, loopback_endpoint

pytestmark = pytest.mark.integration


@pytest.fixture
def processes() -> Iterator[list[subprocess.Popen[bytes]]]:
    procs: list[subprocess.Popen[bytes]] = []
    yield procs
    terminate(procs, grace_s=10.0)


@pytest.mark.timeout(240)  # its child processes' own bound, and set-up
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


def _up_and_in_process(
    scenario: Path, sets: list[str], out: Path, *, fleet: str
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The metrics of `scenario` with `sets`, run by `phalanx up` (into `out`, on its
    own `fleet`) and in process."""
    proc = subprocess.run(
        [*CLI, "up", str(scenario), "--out", str(out), "--fleet", fleet, "--timeout", "120",
         "--no-recording", *(a for s in sets for a in ("--set", s))],
        capture_output=True, text=True, timeout=180, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    multi = json.loads((out / "metrics.json").read_text())
    return multi, run_metrics(run_batch(apply_overrides(load_scenario(scenario), sets)))


@pytest.mark.timeout(240)  # its child processes' own bound, and set-up
def test_up_records_the_shape_a_navigating_group_was_in_and_where_it_fitted(
    tmp_path: Path,
) -> None:
    """The world of a run of processes records, from the states the robots publish, the
    shape the group was in and whether the leader's map showed the scenario's shape
    fitting the way (before, it recorded neither, and said the wedge in its shape all
    the time, fitting all the time, its calm error 99.9 % where the group was folded).
    The figures come out near the in-process run's, not to the bit: in processes a
    robot adds the others' scans to its map as they arrive, so its map, the fit and the
    moment of a reshape move with the machine's load (CI, 125 s of the run: fit 0.648
    against 0.688)."""
    field = CONFIG_ROOT / "scenarios" / "nav_field_wedge3.toml"
    sets = ["duration_s=125"]  # (a fold at 108 s, the wedge again at 117 s)
    both = _up_and_in_process(field, sets, tmp_path / "shape", fleet="shape")
    multi, single = (metrics["navigation"] for metrics in both)
    assert multi["reshapes"] >= 1
    for key in ("scenario_shape_share", "fits_share"):  # (12 s of the 125 either way)
        assert multi[key] == pytest.approx(single[key], abs=0.1), key
        assert multi[key] < 0.95, key  # (folded for a while; narrow for a while)
    assert multi["calm"]["linear_pct"]["max"] < 20.0  # (in process: 3-6 %)


@pytest.mark.timeout(240)  # its child processes' own bound, and set-up
def test_up_reproduces_a_leadership_handover(tmp_path: Path) -> None:
    """The leader alone blocked (its sonars read 0.3 m at 8 s): every robot process hands
    the lead to r2 under epoch 1 on the same tick as the in-process run, and the group's
    transitions and errors agree."""
    sets = ["duration_s=40", *signal_builder(8.0, robots=("r1",))]
    multi, single = _up_and_in_process(WEDGE, sets, tmp_path / "handover", fleet="hand")
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


def test_killed_leader_stops_the_followers_then_leadership_passes_and_it_rejoins(
    tmp_path: Path,
) -> None:
    """The leader's process is killed: the followers stop within 500 ms, a new leader takes
    over under a higher epoch (announced on phalanx/<fleet>/leader), and the restarted
    robot rejoins as a follower, never taking the lead back."""
    with running_fleet(tmp_path, fleet="kill") as fleet:
        watch = fleet.watch

        def latest(rid: str) -> Seen:
            seen = watch.latest(rid)
            assert seen is not None, rid
            return seen

        def told() -> str:
            """What the robots said last, what was announced, and the processes' output."""
            states = {rid: watch.latest(rid) for rid in ROBOTS}
            return f"{states}, announced {watch.announcements}{fleet.tails()}"

        assert fleet.wait_tracking(40.0, after_s=3.0), f"followers never tracked: {told()}"
        fleet.signal("r1", signal.SIGKILL)
        killed_at = time.monotonic()
        fleet.wait_exit("r1", 5.0)

        def stopped() -> bool:
            return all(
                latest(r).state.fsm_state == "HOLD" and latest(r).at > killed_at
                for r in ("r2", "r3")
            )

        assert wait_for(stopped, 2.0), f"followers did not stop: {told()}"
        noticed_s = max(latest(r).at for r in ("r2", "r3")) - killed_at
        assert noticed_s < 0.5, f"followers stopped {noticed_s:.3f} s after the kill"

        # The rule elects the best live robot (r2: clear, most forward, first) under epoch 1.
        def new_leader() -> bool:
            r2, r3 = latest("r2").state, latest("r3").state
            return (
                r2.fsm_state == "NAVIGATE"
                and r2.leader_id == ""
                and r2.epoch == 1
                and r3.formation_leader_id == "r2"
                and r3.epoch == 1
                and r3.leader_id == "r2"
                and r3.fsm_state == "FORMATION_TRACK"
            )

        assert wait_for(new_leader, 10.0), f"no new leader: {told()}"
        announced = watch.announcements
        assert [(a.leader_id, a.epoch, a.previous_id) for a in announced] == [("r2", 1, "r1")]

        # The old leader's process is started again: it joins as a follower of the
        # fleet's leader. Until it drives off, its robot stands where it stopped, at the
        # front of the wedge: a leader it blocks for 2 s hands over to a clear robot
        # (announced, under the next epoch), which a busy machine's slow start gives time.
        fleet.start("r1")
        restarted_at = time.monotonic()

        def rejoined() -> bool:
            seen = watch.latest("r1")
            if seen is None or seen.at <= restarted_at:
                return False
            r1, r2, r3 = seen.state, latest("r2").state, latest("r3").state
            head = r3.formation_leader_id
            return (
                r1.fsm_state == "FORMATION_TRACK"
                and r1.epoch == r2.epoch == r3.epoch == len(announced)
                and r1.formation_leader_id == r2.formation_leader_id == head
                and head in ("r2", "r3")
                and r1.leader_id != ""
            )

        assert wait_for(rejoined, 30.0), f"r1 did not rejoin as a follower: {told()}"
        # rejoining flipped nothing back: every later handover went to another robot,
        # announced by it under the next epoch
        assert all(a.leader_id != "r1" for a in announced), announced
        assert [a.epoch for a in announced] == list(range(1, len(announced) + 1)), announced


def test_malformed_payloads_on_every_key_are_counted_and_ignored(tmp_path: Path) -> None:
    with running_fleet(tmp_path, fleet="junk", duration_s=20.0) as fleet:
        session = fleet.session
        assert session is not None
        assert wait_for(lambda: len(fleet.status(timeout_s=1.0)) >= 4, 40.0)
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
        statuses = fleet.status()
        # the world finishes its 20 s and writes results
        assert fleet.wait_exit("world", 60.0) == 0, fleet.tails()
    assert (fleet.out / "metrics.json").exists()
    agents = [s for s in statuses if "robot_id" in s]
    assert len(agents) == 3
    for status in agents:
        decode = status["decode"]
        assert isinstance(decode, dict)
        assert sum(decode["malformed"].values()) + sum(decode["unknown_version"].values()) >= len(
            garbage
        )


def test_every_robots_sonar_scans_reach_every_other_robots_map(tmp_path: Path) -> None:
    nav = CONFIG_ROOT / "scenarios" / "nav_corridor_wedge3.toml"
    heard: dict[str, int] = {}
    left_out: dict[str, object] = {}  # echoes each map took for another robot of the fleet
    with running_fleet(tmp_path, fleet="maps", duration_s=15.0, scenario=nav) as fleet:

        def everyone_heard_the_others() -> bool:
            for status in fleet.status(timeout_s=1.0):
                if "scans_heard" in status:
                    heard[str(status["robot_id"])] = int(status["scans_heard"])
                    left_out[str(status["robot_id"])] = status.get("robot_echoes_left_out")
            return len(heard) == 3 and min(heard.values()) >= 20

        assert wait_for(everyone_heard_the_others, 40.0), heard
        assert fleet.wait_exit("world", 60.0) == 0, fleet.tails()
    assert all(isinstance(n, int) and n >= 0 for n in left_out.values()), left_out


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
