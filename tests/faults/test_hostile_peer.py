"""A hostile peer on a running fleet (the world and three agents as processes over
Zenoh): each message of the issue's table that crashed a process, ended a run, spoiled
its results or slipped past the counters, sent for real. Every process runs on to the
run's end, the results folder holds only the fleet's robots, and every payload is
counted where a user looks (the status queryables, metrics.json).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from fleetlab import Fleet, running_fleet, wait_for

from phalanx.wire.codec import encode
from phalanx.wire.keys import leader_key, robot_key
from phalanx.wire.messages import (
    AgentEvent,
    AgentReport,
    LeaderAnnouncement,
    RobotFlags,
    RobotState,
    SenseFrame,
)

pytestmark = pytest.mark.slow
FLOOD = 10_000


def _now(fleet: Fleet) -> float:
    seen = fleet.watch.latest("r2")
    assert seen is not None
    return float(seen.state.stamp_s)


def _flags(**values: Any) -> RobotFlags:
    base = {"robot_id": "r3", "seq": 10**6, "stamp_s": 0.0, "fsm_state": "FORMATION_TRACK"}
    return RobotFlags.model_construct(**{**base, **values})


def _frame(**values: Any) -> SenseFrame:
    base = {"robot_id": "r2", "tick": 1, "t_s": 0.1, "dt_s": 0.1, "x_m": 0.0, "y_m": 0.0,
            "theta_rad": 0.0, "v_mps": 0.0, "omega_radps": 0.0, "sonar_ranges_m": (5.0,) * 16,
            "bumpers": (), "final": False}  # fmt: skip
    return SenseFrame.model_construct(**{**base, **values})


def _decode(fleet: Fleet, name: str) -> dict[str, Any]:
    replies = [s for s in fleet.status(name) if s.get("robot_id", "world") == name]
    assert replies, f"no status from {name}"
    decode: dict[str, Any] = replies[0]["decode"]
    return decode


def _publish(fleet: Fleet, key: str, payload: bytes, times: int = 1, gap_s: float = 0.0) -> None:
    assert fleet.session is not None
    for _ in range(times):
        fleet.session.publish_raw(key, payload)
        time.sleep(gap_s)


def test_the_issues_hostile_messages_are_all_dropped_counted_and_survived(tmp_path: Path) -> None:
    with running_fleet(tmp_path, fleet="hostile", duration_s=25.0) as fleet:
        assert fleet.wait_tracking(timeout_s=60.0, after_s=2.0)
        name = fleet.fleet
        # epoch 2**40 in JSON (schema-valid before), kept r3's newest flags for a second
        for _ in range(20):
            doc = {
                "version": 1,
                "robot_id": "r3",
                "seq": 10**6,
                "stamp_s": _now(fleet) + 0.3,
                "fsm_state": "FORMATION_TRACK",
                "epoch": 2**40,
                "formation_leader_id": "r3",
            }
            _publish(fleet, robot_key(name, "r3", "flags"), json.dumps(doc).encode(), gap_s=0.05)
        # packed flags at the top epoch: refused, not adopted by every robot
        top = _flags(stamp_s=_now(fleet) + 0.3, epoch=2**32 - 1, formation_leader_id="r1")
        _publish(fleet, robot_key(name, "r3", "flags"), encode(top, "packed"), 20, 0.05)
        # a state stamped 1e308, a frame at the largest float, a forged final frame
        state = RobotState.model_construct(**{**_flags().model_dump(), "robot_id": "r2",
                                              "stamp_s": 1e308, "x_m": 0.0, "y_m": 0.0,
                                              "theta_rad": 0.0, "v_mps": 0.0,
                                              "omega_radps": 0.0, "leader_id": "r1"})  # fmt: skip
        _publish(fleet, robot_key(name, "r2", "state"), encode(state, "packed"), 3)
        k = round(_now(fleet) / 0.1)
        huge = _frame(tick=k + 3, t_s=sys.float_info.max)
        _publish(fleet, robot_key(name, "r2", "sense"), encode(huge, "packed"))
        final = _frame(tick=k + 1, t_s=(k + 1) * 0.1, final=True)
        _publish(fleet, robot_key(name, "r2", "sense"), encode(final, "packed"))
        # announcements and reports of robots outside the fleet, an event naming r9
        for leader in ("r!", "b1", "r9"):
            forged = LeaderAnnouncement.model_construct(
                leader_id=leader, epoch=7, stamp_s=1.0, previous_id="r1", reason="forged"
            )
            _publish(fleet, leader_key(name), encode(forged, "json"))
        for i in range(20):
            report = AgentReport(robot_id=f"x{i}", steps=1, saturations=0, accel_limited=0,
                                 dropped_messages=0, late_peer_steps=0)  # fmt: skip
            key_of = f"x{i}" if i < 17 else "r1"  # and three on another robot's key
            _publish(fleet, robot_key(name, key_of, "report"), encode(report, "packed"))
        event = AgentEvent.model_construct(robot_id="r9", t_s=1.0, source="HOLD",
                                           target="STUCK", reason="forged")  # fmt: skip
        _publish(fleet, robot_key(name, "r9", "event"), encode(event, "packed"))
        # a flood on r1's flags, as fast as this peer can send
        before = _decode(fleet, "r2")
        ok_before = sum(before["ok"].values())
        _publish(fleet, robot_key(name, "r1", "flags"), b"\x07\x01" + bytes(38), FLOOD)
        time.sleep(2.0)
        after = _decode(fleet, "r2")
        world = _decode(fleet, "world")
        # Nobody ended: r2 ignored the forged final and every process runs to the end.
        assert all(code is None for code in fleet.exit_codes().values()), fleet.exit_codes()
        assert wait_for(lambda: fleet.exit_codes()["world"] is not None, 60.0)
        codes = {n: fleet.wait_exit(n, 30.0) for n in fleet.procs}
        epochs = {r: fleet.watch.latest(r).state.epoch for r in ("r2", "r3")}  # type: ignore[union-attr]
        metrics = json.loads((fleet.out / "metrics.json").read_text())
    assert codes == {"world": 0, "r1": 0, "r2": 0, "r3": 0}, codes
    assert fleet.crashed() == []
    assert max(epochs.values()) < 2**16, epochs  # no forged epoch was adopted
    # Every flooded payload was decoded (and counted malformed) or lost to a full ring
    # (and counted there): none uncounted. Legitimate flags went on arriving meanwhile.
    counted = after["dropped"] - before["dropped"] + sum(after["ok"].values()) - ok_before
    assert counted >= FLOOD, (counted, after)
    assert after["rate_limited"].get("RobotFlags", 0) > 0  # the flood was cut, and said so
    assert after["rejected"].get("SenseFrame", 0) >= 1  # the forged final, refuted
    assert world["dropped"] > 0  # the world's drops show in its status
    runtime = metrics["runtime"]
    assert sorted(runtime["agents"]) == ["r1", "r2", "r3"]
    assert all(a["leader_id"] in ("r1", "r2", "r3") for a in runtime["leadership"])
    assert runtime["world_decode"]["dropped"] > 0  # ... and in metrics.json
    assert metrics["complete"] is True, metrics["incomplete_reason"]
    assert all(r["dropped_messages"] > 0 for r in runtime["agents"].values())
