"""The reliability table of docs/RELIABILITY.md: a hostile peer and a careless user against
the paper fleet (the world and three agents as processes over Zenoh on loopback, started
through the CLI), each row a probe that prints what it measured.

    .venv/bin/python bench/bench_faults.py                 # every probe
    .venv/bin/python bench/bench_faults.py kill_leader hold_zero --trials 5
    .venv/bin/python bench/bench_faults.py --list

Probes (the issue's rows): kill_leader (HOLD, zero command and new leader after a
SIGKILL), freeze_leader (SIGSTOP noticed; stale states after SIGCONT), junk (random,
truncated, non-finite, wrong-version payloads on every key), epoch_json (flags at epoch
2**40, JSON), epoch_max (packed flags at 2**32-1, then the leader killed), stamp_huge
(state stamped 1e308), sense_huge (sense frame t_s = 1.8e308), forged_final (a sense frame
with final = true), event_unknown (an event naming r9), flood (10 000 payloads on one
robot's flags), world_status (decode counters in the world's status), junk_leaders
(announcements of r!, b1, r9), forged_reports (reports of 20 robot ids), up_agent_killed
and up_world_killed (`phalanx up` exit code and results folder), bad_files (malformed
scenario files and --set values).
"""

from __future__ import annotations

import argparse
import json
import random
import re
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "lab"))
from fleetlab import CLI, WEDGE, Fleet, child_running, running_fleet, wait_for

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

Result = dict[str, Any]
PROBES: dict[str, Callable[[Path, argparse.Namespace], Result]] = {}


def probe(fn: Callable[[Path, argparse.Namespace], Result]) -> Callable[..., Result]:
    PROBES[fn.__name__] = fn
    return fn


def _flags(**values: Any) -> RobotFlags:
    base = {"robot_id": "r3", "seq": 1, "stamp_s": 0.0, "fsm_state": "FORMATION_TRACK"}
    return RobotFlags.model_construct(**{**base, **values})


def _state(**values: Any) -> RobotState:
    base = {
        "robot_id": "r2",
        "seq": 1,
        "stamp_s": 0.0,
        "x_m": 0.0,
        "y_m": 0.0,
        "theta_rad": 0.0,
        "v_mps": 0.0,
        "omega_radps": 0.0,
        "fsm_state": "FORMATION_TRACK",
        "obstacle": False,
        "direction": 1,
        "leader_id": "r1",
        "epoch": 0,
        "formation_leader_id": "r1",
        "clear": False,
        "formed": True,
        "blocked_s": 0.0,
        "dead_end": False,
        "waypoint": 0,
        "deadlocks": 0,
        "profile_s": 0.0,
    }
    return RobotState.model_construct(**{**base, **values})


def _frame(**values: Any) -> SenseFrame:
    base = {
        "robot_id": "r2",
        "tick": 1,
        "t_s": 0.1,
        "dt_s": 0.1,
        "x_m": 0.0,
        "y_m": 0.0,
        "theta_rad": 0.0,
        "v_mps": 0.0,
        "omega_radps": 0.0,
        "sonar_ranges_m": (5.0,) * 16,
        "bumpers": (),
        "final": False,
    }
    return SenseFrame.model_construct(**{**base, **values})


def _need(condition: bool, why: str) -> None:
    if not condition:
        raise RuntimeError(why)


def _settle(fleet: Fleet, s: float = 2.0) -> None:
    time.sleep(s)


def _fleet_time(fleet: Fleet) -> float:
    seen = fleet.watch.latest("r2") or fleet.watch.latest("r3")
    return seen.state.stamp_s if seen else 0.0


# --- supervision -----------------------------------------------------------------------


def _first(fleet: Fleet, rid: str, after: float, test: Callable[[Any], bool]) -> float | None:
    for seen in fleet.watch.since(rid, after):
        if test(seen.state):
            return seen.at - after
    return None


@probe
def kill_leader(work: Path, args: argparse.Namespace) -> Result:
    """SIGKILL the leader at a random moment of the forward phase: when each follower
    publishes HOLD, a zero command (its state carries the command it executes), and when
    a new leader leads."""
    trials = []
    for trial in range(args.trials):
        with running_fleet(work / f"kill{trial}", fleet=f"kill{trial}") as fleet:
            _need(fleet.wait_tracking(), "followers never tracked")
            time.sleep(random.uniform(0.0, 2.0))
            killed = time.monotonic()
            fleet.signal("r1", signal.SIGKILL)
            wait_for(lambda t=killed: _led(fleet, t), 10.0)
            time.sleep(0.5)
            row = {}
            for rid in ("r2", "r3"):
                row[f"{rid}_hold_s"] = _first(fleet, rid, killed, lambda s: s.fsm_state == "HOLD")
                row[f"{rid}_zero_s"] = _first(fleet, rid, killed, _zero)
            leads = [_first(fleet, r, killed, _leads) for r in ("r2", "r3")]
            row["new_leader_s"] = min((x for x in leads if x is not None), default=None)
            row["crashed"] = fleet.crashed(allowed=(0, -9))
            trials.append(row)
    return {
        "trials": trials,
        **_span(trials, ("r2_hold_s", "r3_hold_s"), "hold_s"),
        **_span(trials, ("r2_zero_s", "r3_zero_s"), "zero_s"),
        **_span(trials, ("new_leader_s",), "new_leader_s"),
    }


def _led(fleet: Fleet, after: float) -> bool:
    return any(_first(fleet, r, after, _leads) is not None for r in ("r2", "r3"))


def _leads(state: Any) -> bool:
    return state.leader_id == "" and state.fsm_state in ("NAVIGATE", "WANDER")


def _holds(state: Any) -> bool:
    return state.fsm_state == "HOLD"


def _zero(state: Any) -> bool:
    return state.v_mps == 0.0 and state.omega_radps == 0.0


def _span(rows: list[Result], keys: tuple[str, ...], name: str) -> Result:
    values = [r[k] for r in rows for k in keys if r.get(k) is not None]
    missing = sum(1 for r in rows for k in keys if r.get(k) is None)
    if not values:
        return {name: None, f"{name}_missing": missing}
    return {name: [round(min(values), 3), round(max(values), 3)], f"{name}_missing": missing}


@probe
def freeze_leader(work: Path, args: argparse.Namespace) -> Result:
    """SIGSTOP the leader 0.8 s (under the 1 s Zenoh lease) and 3 s, then SIGCONT: when the
    followers notice, and how many states it publishes afterwards stamped more than the
    leader timeout (0.5 s) behind the fleet, and of those how many as the leader."""
    rows = {}
    for frozen_s in (0.8, 3.0):
        with running_fleet(work / f"freeze{frozen_s}", fleet=f"fz{int(frozen_s * 10)}") as fleet:
            _need(fleet.wait_tracking(), "followers never tracked")
            frozen = time.monotonic()
            fleet.signal("r1", signal.SIGSTOP)
            time.sleep(frozen_s)
            resumed = time.monotonic()
            now_s = _fleet_time(fleet)
            fleet.signal("r1", signal.SIGCONT)
            time.sleep(3.0)
            noticed = [
                _first(fleet, r, frozen, lambda s: s.fsm_state == "HOLD") for r in ("r2", "r3")
            ]
            after = fleet.watch.since("r1", resumed)
            stale = [s for s in after if s.state.stamp_s < now_s - 0.5]
            rows[f"frozen_{frozen_s}s"] = {
                "followers_hold_s": noticed,
                "r1_states_after_resume": len(after),
                "stale_states": len(stale),
                "stale_states_as_leader": sum(1 for s in stale if s.state.leader_id == ""),
                "crashed": fleet.crashed(),
            }
    return rows


# --- payloads --------------------------------------------------------------------------

TOPICS = ("state", "flags", "sense", "cmd", "event", "report")
GARBAGE = [
    b"",
    b"\x00",
    b"\x01\x01\xff",
    b"{not json",
    b'{"version": 99}',
    bytes(range(256)),
    b'{"version":1,"robot_id":"r2","t_s":NaN}',
    b"\x01\x02" + bytes(110),
]


def _decode_total(status: dict[str, Any]) -> int:
    decode = status.get("decode") or {}
    if "dropped" in decode:
        return int(decode["dropped"])
    return sum(sum(decode.get(k, {}).values()) for k in ("malformed", "unknown_version"))


@probe
def junk(work: Path, args: argparse.Namespace) -> Result:
    """Random, truncated, non-finite and wrong-version payloads on every key of every
    robot and on `leader`: who crashed, and what the status queryables counted."""
    with running_fleet(work / "junk", fleet="junk") as fleet:
        _need(fleet.wait_tracking(), "followers never tracked")
        session = fleet.session
        _need(session is not None, "no session")
        before = {s.get("robot_id", "world"): _decode_total(s) for s in fleet.status()}
        valid = encode(_state(stamp_s=_fleet_time(fleet)), "packed")
        payloads = [*GARBAGE, valid[:-3], valid + b"\x00", bytes([valid[0], 9]) + valid[2:]]
        for rid in ("r1", "r2", "r3"):
            for topic in TOPICS:
                for payload in payloads:
                    session.publish_raw(robot_key(fleet.fleet, rid, topic), payload)
        for payload in payloads:
            session.publish_raw(leader_key(fleet.fleet), payload)
        _settle(fleet)
        after = {s.get("robot_id", "world"): _decode_total(s) for s in fleet.status()}
        return {
            "sent_per_process_keys": len(payloads),
            "counted": {k: after.get(k, 0) - before.get(k, 0) for k in after},
            "crashed": fleet.crashed(),
        }


@probe
def epoch_json(work: Path, args: argparse.Namespace) -> Result:
    """Flags at epoch 2**40 in JSON (schema-valid then): who crashed."""
    with running_fleet(work / "ej", fleet="ej") as fleet:
        _need(fleet.wait_tracking(), "followers never tracked")
        for _ in range(20):  # stamped ahead so each stays r3's newest flags for a while
            doc = {
                "version": 1,
                "robot_id": "r3",
                "seq": 10**6,
                "stamp_s": _fleet_time(fleet) + 0.3,
                "fsm_state": "FORMATION_TRACK",
                "epoch": 2**40,
                "formation_leader_id": "r3",
            }
            fleet.session.publish_raw(
                robot_key(fleet.fleet, "r3", "flags"), json.dumps(doc).encode()
            )  # type: ignore[union-attr]
            time.sleep(0.05)
        _settle(fleet, 3.0)
        return {"crashed": fleet.crashed()}


@probe
def epoch_max(work: Path, args: argparse.Namespace) -> Result:
    """Packed flags of r3 at epoch 2**32-1 naming r1 the leader, then r1 killed: who
    crashed."""
    with running_fleet(work / "em", fleet="em") as fleet:
        _need(fleet.wait_tracking(), "followers never tracked")
        for _ in range(20):
            flags = _flags(
                robot_id="r3",
                stamp_s=_fleet_time(fleet) + 0.3,
                epoch=2**32 - 1,
                formation_leader_id="r1",
            )
            fleet.session.publish_raw(
                robot_key(fleet.fleet, "r3", "flags"), encode(flags, "packed")
            )  # type: ignore[union-attr]
            time.sleep(0.05)
        fleet.signal("r1", signal.SIGKILL)
        _settle(fleet, 4.0)
        epochs = {
            r: (fleet.watch.latest(r).state.epoch if fleet.watch.latest(r) else None)
            for r in ("r2", "r3")
        }
        return {"crashed": fleet.crashed(allowed=(0, -9)), "epochs": epochs}


@probe
def stamp_huge(work: Path, args: argparse.Namespace) -> Result:
    """A state of r2 stamped 1e308: tracebacks per process."""
    with running_fleet(work / "sh", fleet="sh") as fleet:
        _need(fleet.wait_tracking(), "followers never tracked")
        for _ in range(3):
            fleet.session.publish_raw(
                robot_key(fleet.fleet, "r2", "state"), encode(_state(stamp_s=1e308), "packed")
            )  # type: ignore[union-attr]
        _settle(fleet)
        return {"tracebacks": fleet.tracebacks(), "crashed": fleet.crashed()}


@probe
def sense_huge(work: Path, args: argparse.Namespace) -> Result:
    """A sense frame for r2 with t_s = 1.8e308 (the largest float): does r2 take the lead,
    or crash."""
    with running_fleet(work / "sf", fleet="sf") as fleet:
        _need(fleet.wait_tracking(), "followers never tracked")
        sent = time.monotonic()
        fleet.session.publish_raw(
            robot_key(fleet.fleet, "r2", "sense"),
            encode(
                _frame(t_s=sys.float_info.max, tick=round(_fleet_time(fleet) / 0.1) + 3), "packed"
            ),
        )  # type: ignore[union-attr]
        _settle(fleet, 3.0)
        took = _first(fleet, "r2", sent, _leads)
        announced = [a.leader_id for a in fleet.watch.announcements]
        return {
            "r2_took_the_lead": took is not None or "r2" in announced,
            "announcements": announced,
            "crashed": fleet.crashed(),
        }


@probe
def forged_final(work: Path, args: argparse.Namespace) -> Result:
    """A sense frame for r2 with final = true, mid-run: r2's exit code (0 = a silent
    ending a supervisor takes for a finished run)."""
    with running_fleet(work / "ff", fleet="ff") as fleet:
        _need(fleet.wait_tracking(), "followers never tracked")
        k = round(_fleet_time(fleet) / 0.1)
        fleet.session.publish_raw(
            robot_key(fleet.fleet, "r2", "sense"),
            encode(_frame(tick=k, t_s=k * 0.1, final=True), "packed"),
        )  # type: ignore[union-attr]
        code = fleet.wait_exit("r2", 8.0)
        return {"r2_exit_code": code, "r2_still_running": code is None}


@probe
def event_unknown(work: Path, args: argparse.Namespace) -> Result:
    """An event naming r9 (a robot not in the fleet), then the run's end: the world's
    exit code and what its results folder holds."""
    with running_fleet(work / "eu", fleet="eu", duration_s=12.0) as fleet:
        _need(fleet.wait_tracking(timeout_s=60.0, after_s=1.0), "followers never tracked")
        event = AgentEvent.model_construct(
            robot_id="r9", t_s=1.0, source="A", target="B", reason="x"
        )
        fleet.session.publish_raw(robot_key(fleet.fleet, "r9", "event"), encode(event, "packed"))  # type: ignore[union-attr]
        code = fleet.wait_exit("world", 60.0)
        return {
            "world_exit_code": code,
            "metrics_json": (fleet.out / "metrics.json").exists(),
            "figures": len(list(fleet.out.glob("*.png"))) if fleet.out.exists() else 0,
        }


@probe
def flood(work: Path, args: argparse.Namespace) -> Result:
    """10 000 payloads (random bytes) on r1's flags as fast as the observer can send:
    how many r2's status counted (decoded, malformed, dropped by a full ring)."""
    with running_fleet(work / "fl", fleet="fl") as fleet:
        _need(fleet.wait_tracking(), "followers never tracked")

        def counted() -> int:
            statuses = [s for s in fleet.status("r2") if s.get("robot_id") == "r2"]
            if not statuses:
                return -1
            decode = statuses[0].get("decode") or {}
            ok = sum((decode.get("ok") or {}).values())
            if "dropped" in decode:  # every way a payload is not acted on, ring included
                return ok + int(decode["dropped"])
            return ok + _decode_total(statuses[0])

        before = counted()
        n = 10_000
        rng = random.Random(1)
        key = robot_key(fleet.fleet, "r1", "flags")
        for _ in range(n):
            fleet.session.publish_raw(key, bytes(rng.randrange(256) for _ in range(40)))  # type: ignore[union-attr]
        _settle(fleet, 2.0)
        after = counted()
        # Legitimate flags keep arriving meanwhile (a few a second): an upper bound.
        return {
            "sent": n,
            "counted_by_r2": after - before,
            "uncounted": n - (after - before),
            "crashed": fleet.crashed(),
        }


@probe
def world_status(work: Path, args: argparse.Namespace) -> Result:
    """What the world's status queryable answers."""
    with running_fleet(work / "ws", fleet="ws") as fleet:
        _need(fleet.wait_tracking(), "followers never tracked")
        replies = fleet.status("world")
        keys = sorted(replies[0]) if replies else []
        return {"keys": keys, "has_decode_counters": "decode" in keys}


@probe
def junk_leaders(work: Path, args: argparse.Namespace) -> Result:
    """Announcements of leaders r!, b1 and r9, then the run's end: what metrics.json's
    runtime.leadership lists."""
    with running_fleet(work / "jl", fleet="jl", duration_s=12.0) as fleet:
        _need(fleet.wait_tracking(timeout_s=60.0, after_s=1.0), "followers never tracked")
        for leader in ("r!", "b1", "r9"):
            message = LeaderAnnouncement.model_construct(
                leader_id=leader, epoch=7, stamp_s=1.0, previous_id="r1", reason="forged"
            )
            fleet.session.publish_raw(leader_key(fleet.fleet), encode(message, "json"))  # type: ignore[union-attr]
        fleet.wait_exit("world", 60.0)
        return _metrics_runtime(fleet, "leadership", lambda v: [a["leader_id"] for a in v])


def _metrics_runtime(fleet: Fleet, key: str, view: Callable[[Any], Any]) -> Result:
    path = fleet.out / "metrics.json"
    if not path.exists():
        return {"metrics_json": False}
    runtime = json.loads(path.read_text()).get("runtime", {})
    return {key: view(runtime.get(key))}


@probe
def forged_reports(work: Path, args: argparse.Namespace) -> Result:
    """Reports naming 17 robots outside the fleet (on their own keys) and three on the
    wrong key: how many agents metrics.json's runtime.agents lists for 3 robots."""
    with running_fleet(work / "fr", fleet="fr", duration_s=12.0) as fleet:
        _need(fleet.wait_tracking(timeout_s=60.0, after_s=1.0), "followers never tracked")
        for i in range(20):
            rid = f"x{i}"
            report = AgentReport(
                robot_id=rid,
                steps=1,
                saturations=0,
                accel_limited=0,
                dropped_messages=0,
                late_peer_steps=0,
            )
            key_rid = rid if i < 17 else "r1"
            fleet.session.publish_raw(
                robot_key(fleet.fleet, key_rid, "report"), encode(report, "packed")
            )  # type: ignore[union-attr]
        fleet.wait_exit("world", 60.0)
        return _metrics_runtime(fleet, "agents", lambda v: sorted(v or {}))


def collect(strategy: Any, n: int, seed: int = 0) -> list[bytes]:
    """`n` payloads drawn from a hypothesis strategy (outside a test: one @given run)."""
    from hypothesis import HealthCheck, given, settings

    out: list[bytes] = []

    @settings(
        max_examples=n,
        database=None,
        derandomize=True,
        deadline=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(strategy)
    def draw(payload: bytes) -> None:
        out.append(payload)

    draw()
    return out


def valid_payloads(t_s: float) -> dict[str, tuple[type, list[Any]]]:
    """A valid message per topic at fleet time `t_s` (what perturbations start from)."""
    from phalanx.wire.messages import VelocityCommand

    k = round(t_s / 0.1)
    cmd = VelocityCommand(robot_id="r2", tick=k, stamp_s=k * 0.1, v_mps=0.1, omega_radps=0.0)
    event = AgentEvent(robot_id="r2", t_s=t_s, source="HOLD", target="FORMATION_TRACK", reason="x")
    report = AgentReport(
        robot_id="r2",
        steps=1,
        saturations=0,
        accel_limited=0,
        dropped_messages=0,
        late_peer_steps=0,
    )
    leader = LeaderAnnouncement(leader_id="r2", epoch=1, stamp_s=t_s, previous_id="r1")
    return {
        "state": (RobotState, [_state(stamp_s=t_s)]),
        "flags": (RobotFlags, [_flags(stamp_s=t_s)]),
        "sense": (SenseFrame, [_frame(tick=k + 1, t_s=(k + 1) * 0.1)]),
        "cmd": (VelocityCommand, [cmd]),
        "event": (AgentEvent, [event]),
        "report": (AgentReport, [report]),
        "leader": (LeaderAnnouncement, [leader]),
    }


@probe
def fuzz(work: Path, args: argparse.Namespace) -> Result:
    """`--per-key` hostile payloads (hypothesis strategies from the wire models: random,
    truncated, bit-flipped, schema-shaped with extreme values) on every key the world
    and the agents subscribe to, over Zenoh: who crashed."""
    from wirefuzz import hostile_payloads

    with running_fleet(work / "fz", fleet="fz") as fleet:
        _need(fleet.wait_tracking(), "followers never tracked")
        session = fleet.session
        _need(session is not None, "no session")
        sent = {}
        for topic, (model, valid) in valid_payloads(_fleet_time(fleet)).items():
            payloads = collect(hostile_payloads(model, lambda v=valid: v), args.per_key)
            key = (
                leader_key(fleet.fleet)
                if topic == "leader"
                else robot_key(fleet.fleet, "r2", topic)
            )
            for i, payload in enumerate(payloads):
                session.publish_raw(key, payload)
                if i % 50 == 49:
                    time.sleep(0.05)  # a peer, not a flood: let every payload be decoded
            sent[topic] = len(payloads)
        _settle(fleet, 3.0)
        return {
            "sent": sent,
            "crashed": fleet.crashed(),
            "tracebacks": fleet.tracebacks(),
            "exit_codes": fleet.exit_codes(),
        }


# --- phalanx up ------------------------------------------------------------------------


def _up(work: Path, name: str, victim: str, duration_s: float = 20.0) -> Result:
    out = work / name
    argv = [
        *CLI,
        "up",
        str(WEDGE),
        "--out",
        str(out),
        "--fleet",
        name,
        "--clock",
        "realtime",
        "--timeout",
        "120",
        "--set",
        f"duration_s={duration_s}",
    ]
    with (work / f"{name}.log").open("wb") as log:
        proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT)
        wait_for(lambda: child_running(proc.pid, "--robot", "r3") is not None, 30.0, 0.1)
        time.sleep(6.0)
        needle = ("world",) if victim == "world" else ("--robot", victim)
        pid = child_running(proc.pid, *needle)
        if pid is not None:
            import os

            os.kill(pid, signal.SIGKILL)
        code = proc.wait(180)
    text = (work / f"{name}.log").read_text(errors="replace")
    files = sorted(p.name for p in out.iterdir()) if out.exists() else []
    recording_ok = None
    if (out / "run.rrd").exists():
        from phalanx.telemetry.rrd import summarize

        recording_ok = sum(summarize(out / "run.rrd").rows.values()) > 0
    return {
        "exit_code": code,
        "killed_pid": pid,
        "results": files,
        "run_rrd_reads_back": recording_ok,
        "says_which": victim in text and any(w in text for w in ("killed", "SIGKILL", "-9")),
        "tracebacks": text.count("Traceback"),
    }


@probe
def up_agent_killed(work: Path, args: argparse.Namespace) -> Result:
    """`phalanx up` (real time, 20 s) with r2 SIGKILLed after 6 s: exit code, results."""
    return _up(work, "upa", "r2")


@probe
def up_world_killed(work: Path, args: argparse.Namespace) -> Result:
    """`phalanx up` (real time, 20 s) with the world SIGKILLed after 6 s."""
    return _up(work, "upw", "world")


# --- bad files and values --------------------------------------------------------------


def _bad(work: Path) -> dict[str, tuple[str | None, list[str]]]:
    """Case name -> (file text or None for the wedge, extra CLI arguments)."""
    wedge = WEDGE.read_text()
    cycle = wedge.replace('robot = "r2"\nfollows = "r1"', 'robot = "r2"\nfollows = "r3"')
    cycle = cycle.replace('robot = "r3"\nfollows = "r1"', 'robot = "r3"\nfollows = "r2"')
    self_follow = wedge.replace('robot = "r2"\nfollows = "r1"', 'robot = "r2"\nfollows = "r2"')
    many = re.sub(r"\[\[formation\.slots\]\].*", "", wedge, flags=re.S)
    many += '[[formation.slots]]\nrobot = "r0"\nx_m = 0.0\ny_m = 0.0\n'
    for i in range(1, 10_000):
        many += f'[[formation.slots]]\nrobot = "r{i}"\nfollows = "r0"\nl_m = {1 + i * 0.01}\nphi_deg = 180.0\n'  # noqa: E501
    for i in range(10_000):
        many += f'[[robots]]\nid = "r{i}"\nstart = {{ x_m = {-i * 0.7}, y_m = 0.0 }}\n'
    return {
        "unknown_key": (wedge.replace("seed = 1", "seed = 1\nsed = 2"), []),
        "wrong_type": (wedge.replace("duration_s = 200.0", 'duration_s = "long"'), []),
        "nan": (wedge.replace("duration_s = 200.0", "duration_s = nan"), []),
        "syntax_error": (wedge.replace("seed = 1", "seed = = 1"), []),
        "empty_file": ("", []),
        "binary_file": (None, []),
        "follow_cycle": (cycle, []),
        "self_follow": (self_follow, []),
        "robots_10000": (many, []),
        "set_nonsense": (wedge, ["--set", "nonsense"]),
        "set_negative": (wedge, ["--set", "limits.v_max_mps=-1"]),
        "set_noexist": (wedge, ["--set", "noexist.x=1"]),
    }


@probe
def bad_files(work: Path, args: argparse.Namespace) -> Result:
    """`phalanx run` on each malformed file or value (and `phalanx up` on a self-following
    file): exit code, lines on stderr, a traceback or not, whether the message names the
    file, and the peak memory of the 10 000-robot case."""
    rows = {}
    for case, (text, extra) in _bad(work).items():
        path = work / f"{case}.toml"
        if text is None:
            path.write_bytes(bytes(range(256)) * 8)
        else:
            path.write_text(text)
        cmd = "up" if case == "self_follow" else "run"
        argv = [*CLI, cmd, str(path), "--out", str(work / f"out-{case}"), *extra]
        if cmd == "run":
            argv += ["--no-recording", "--no-progress"]
        else:
            argv += ["--no-recording", "--fleet", "bad", "--timeout", "30"]
        rows[case] = _run_bad(argv, path)
    return rows


def _run_bad(argv: list[str], path: Path, timeout_s: float = 60.0) -> Result:
    """Run one bad case: exit code (None: still going after `timeout_s`, i.e. accepted),
    stderr lines, traceback, file named, peak resident memory."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        proc = subprocess.Popen(argv, stdout=out, stderr=err)
        peak_kib = 0
        deadline = time.monotonic() + timeout_s
        while proc.poll() is None and time.monotonic() < deadline:
            peak_kib = max(peak_kib, _hwm_kib(proc.pid))
            time.sleep(0.05)
        code = proc.poll()
        if code is None:
            proc.kill()
            proc.wait(10)
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read().decode(errors="replace"), err.read().decode(errors="replace")
    both = stderr + stdout
    return {
        "exit": code,
        "lines": len(stderr.strip().splitlines()),
        "traceback": "Traceback" in both,
        "names_file": str(path) in both or path.name in both,
        "peak_rss_mib": round(peak_kib / 1024),
        "last_line": (stderr.strip().splitlines() or [""])[-1][:200],
    }


def _hwm_kib(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except (FileNotFoundError, ProcessLookupError, ValueError):
        pass
    return 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("probes", nargs="*", help="probes to run (default: all)")
    parser.add_argument("--trials", type=int, default=3, help="kill_leader trials")
    parser.add_argument("--per-key", type=int, default=300, help="fuzz: payloads per key")
    parser.add_argument("--list", action="store_true", help="list the probes")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    if args.list:
        for name, fn in PROBES.items():
            print(f"{name}: {' '.join((fn.__doc__ or '').split())}")
        return
    names = args.probes or list(PROBES)
    results: dict[str, Result] = {}
    with tempfile.TemporaryDirectory(prefix="faults-") as tmp:
        for name in names:
            started = time.monotonic()
            try:
                results[name] = PROBES[name](Path(tmp), args)
            except Exception as exc:  # a probe that fails says so and the rest go on
                results[name] = {"probe_failed": f"{type(exc).__name__}: {exc}"}
            results[name]["probe_s"] = round(time.monotonic() - started, 1)
            print(f"{name}: {json.dumps(results[name], default=str)}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()
