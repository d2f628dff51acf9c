"""The behaviour stack in the simulated world: handover, leader loss, deadlock reverse
out of a dead end, the STUCK stop, wandering."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
import pytest

from phalanx.agents.agent import Observation
from phalanx.agents.behaviours.base import Moment
from phalanx.agents.behaviours.leader import TURN_ROOM
from phalanx.agents.inputs import FleetView
from phalanx.agents.leadership import LiveFlags
from phalanx.agents.navigation import Breadcrumbs
from phalanx.agents.navigation.clearance import clearance_along
from phalanx.agents.sensing import Sensing
from phalanx.analysis.metrics import error_series, navigation_metrics, phase_masks, run_metrics
from phalanx.core.config import PolygonObstacle
from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_scenario
from phalanx.core.geometry import ZERO_TWIST, Pose2D, Vec2
from phalanx.core.peers import PeerFlags, PeerState
from phalanx.core.robot import Odometry
from phalanx.core.runlog import RunLog
from phalanx.core.scenarios import navigation_scenario, signal_builder
from phalanx.core.states import State
from phalanx.runtime.batch import BatchRunner, run_batch

SCENARIOS = CONFIG_ROOT / "scenarios"
U_MOUTH_X_M = 4.0  # where the dead end's U opens (`phalanx.core.scenarios.navigation_scenario`)


def test_a_blocked_leader_hands_over_and_every_robot_agrees() -> None:
    # The paper's signal builder, for the leader alone: its sonars read 0.3 m at 10 s.
    scenario = apply_overrides(
        load_scenario(SCENARIOS / "paper_wedge.toml"),
        ["duration_s=20", *signal_builder(10.0, robots=("r1",))],
    )
    log = run_batch(scenario)
    k = len(log.t_s) - 1
    assert {tr.leaders[k] for tr in log.traces.values()} == {"r2"}
    assert {tr.epochs[k] for tr in log.traces.values()} == {1}
    assert log.traces["r1"].tracked[k] == "r2"  # the old leader now follows
    assert log.traces["r3"].tracked[k] == "r1"  # r3 keeps its neighbour: re-rooted tree
    change = next(e for e in log.transitions["r2"] if e.target == State.NAVIGATE)
    assert 10.1 < change.t_s < 10.6
    assert "r1 blocked" in change.reason
    assert "epoch 1" in change.reason
    assert not log.collisions
    # The shape holds through the handover: errors against whoever is tracked stay small.
    late = log.t_s > 15.0
    for rid in ("r1", "r3"):
        assert np.nanmax(error_series(log, rid).linear_pct[late]) < 2.0


def test_a_lost_leader_stops_the_followers_then_the_best_robot_leads() -> None:
    runner = BatchRunner(
        apply_overrides(load_scenario(SCENARIOS / "paper_wedge.toml"), ["duration_s=12"])
    )
    published: deque[dict[str, PeerState]] = deque(maxlen=1)
    states_at: dict[float, dict[str, str]] = {}
    for k in range(round(12.0 / runner.scenario.dt_s)):
        t_s = float(runner.t_s[k])
        alive = {r: a for r, a in runner.agents.items() if r != "r1" or t_s < 5.0}
        peers = published[0] if published else {}
        commands, states = {"r1": ZERO_TWIST}, {}
        for rid, agent in alive.items():
            obs = Observation(runner.world.odometry(rid), runner.world.status(rid))
            out = agent.step(obs, {r: s for r, s in peers.items() if r in alive}, t_s)
            commands[rid], states[rid] = out.command, out.state
        published.append(states)
        runner.world.step(commands, runner.scenario.dt_s)
        states_at[round(t_s, 1)] = {r: s.fsm_state for r, s in states.items()}
    assert states_at[5.2] == {"r2": State.HOLD, "r3": State.HOLD}  # within 0.5 s
    r2, r3 = runner.agents["r2"], runner.agents["r3"]
    assert (r2.leader_id, r2.leadership.epoch) == ("r2", 1)
    assert (r3.leader_id, r3.leadership.epoch, r3.parent_id) == ("r2", 1, "r2")
    assert states_at[11.9] == {"r2": State.NAVIGATE, "r3": State.FORMATION_TRACK}
    assert not runner.world.collisions


def _backed_out_within_the_papers_bounds(log: RunLog) -> None:
    """More than 20 s of settled reverse, every follower within the backward bounds."""
    _, backward = phase_masks(log)
    assert backward.sum() * log.scenario.dt_s > 20.0
    for rid in ("r2", "r3"):
        series = error_series(log, rid)
        assert series.linear_pct[backward].max() < 0.5
        assert series.angular_pct[backward].max() < 0.3
        assert series.orientation_deg[backward].max() < 0.5


@pytest.mark.slow
def test_the_group_backs_out_of_the_dead_end_in_formation() -> None:
    # The paper's reverse, in the scenario's own shape (no reshaping into the dead end:
    # the folded group's escape is checked below).
    scenario = apply_overrides(
        load_scenario(SCENARIOS / "nav_deadend_wedge3.toml"), ["navigation.reshape=false"]
    )
    runner = BatchRunner(scenario)

    def turned(b: BatchRunner) -> bool:
        return any(
            e.target == State.DEADLOCK_TURN for a in b.agents.values() for e in a.transitions
        )

    log = runner.run(until=turned)
    assert not log.collisions
    reverses = [e for e in log.transitions["r1"] if e.target == State.DEADLOCK_REVERSE]
    assert len(reverses) == 1
    assert "dead end" in reverses[0].reason
    _backed_out_within_the_papers_bounds(log)


def _pause_before_the_reverse(scenario_overrides: list[str]) -> tuple[float, bool]:
    """The wedge of three in the dead end (its own shape): how long its leader stood
    still in DEADLOCK_REVERSE after its last turning step, and whether every follower
    said it had settled on the step before the leader backed off.
    """
    scenario = apply_overrides(
        load_scenario(SCENARIOS / "nav_deadend_wedge3.toml"),
        ["navigation.reshape=false", *scenario_overrides],
    )
    runner = BatchRunner(scenario)
    leader, followers = runner.agents["r1"], [runner.agents["r2"], runner.agents["r3"]]
    still_from_s, settled_before = math.inf, False
    for k in range(runner.steps):
        runner.step(k)
        t_s = float(runner.t_s[k])
        if leader.state_name != State.DEADLOCK_REVERSE:
            continue
        if not leader.parts.reverse.pausing:
            return t_s - still_from_s, settled_before
        if math.isinf(still_from_s) or leader.limiter.last.omega_radps != 0.0:
            still_from_s = t_s  # (the pause runs from the turn back's end)
        settled_before = all(
            f.state_name == State.FORMATION_TRACK and f.parts.track.settled for f in followers
        )
    raise AssertionError("the group never backed off")


@pytest.mark.slow
def test_the_leader_backs_off_once_its_followers_have_settled_not_after_all_its_pause() -> None:
    waited_s, settled = _pause_before_the_reverse([])  # (`pause_until_settled` on)
    full_s, _ = _pause_before_the_reverse(["deadlock.pause_until_settled=false"])
    assert settled
    assert waited_s < full_s - 1.0, (waited_s, full_s)  # (12 s: the scenario's pause_s)


def test_the_pause_waits_for_every_follower_to_say_it_settled_since_the_leader_stopped() -> None:
    runner = BatchRunner(load_scenario(SCENARIOS / "nav_deadend_wedge3.toml"))
    reverse = runner.agents["r1"].parts.reverse  # (12 s of pause at most)
    free = (np.zeros(0), np.zeros(0))
    sensing = Sensing(free, free, 5.0, {1: False, -1: False}, True, False, False)
    pose = Pose2D(2.0, 0.0, 0.0)

    def moment(t_s: float, **said: tuple[bool, float]) -> Moment:
        flags = {
            rid: PeerFlags(rid, 1, stamp_s, State.FORMATION_TRACK, settled=settled)
            for rid, (settled, stamp_s) in said.items()
        }
        live = LiveFlags(flags, runner.formation)
        view = FleetView(live, None, True, "r1", None, None)
        odometry = Odometry(pose, ZERO_TWIST, t_s)
        return Moment(t_s, State.DEADLOCK_REVERSE, odometry, sensing, view)

    reverse.enter(moment(10.0))
    # one follower not settled yet, or settled only before the leader stopped: it waits
    assert reverse.command(moment(11.0, r2=(True, 10.9), r3=(False, 10.9))) == ZERO_TWIST
    assert reverse.command(moment(11.1, r2=(True, 11.0), r3=(True, 9.9))) == ZERO_TWIST
    assert reverse.pausing
    # both settled since: it backs off, and goes on backing whatever they say then
    assert reverse.command(moment(11.2, r2=(True, 11.1), r3=(True, 11.1))).v_mps < 0.0
    assert reverse.command(moment(11.3, r2=(False, 11.2), r3=(False, 11.2))).v_mps < 0.0
    assert not reverse.pausing
    # a follower that never settles holds the group for the whole pause, no longer
    reverse.enter(moment(20.0))
    assert reverse.command(moment(31.9, r2=(True, 31.8), r3=(False, 31.8))) == ZERO_TWIST
    assert reverse.command(moment(32.0, r2=(True, 31.9), r3=(False, 31.9))).v_mps < 0.0


@pytest.mark.slow
def test_a_wedge_folded_into_the_dead_end_backs_out_folded_and_gets_there() -> None:
    # The dead end looks passable for a column until its far wall is seen: the wedge
    # folds, drives in, backs out as a column, goes round and unfolds on the way. The
    # turn back to the way it came in swings the column's slots sideways; the followers
    # settle onto them during the pause, so the reverse is within the paper's bounds.
    log = run_batch(load_scenario(SCENARIOS / "nav_deadend_wedge3.toml"))
    leader = [(e.target, e.reason) for e in log.transitions["r1"]]
    targets = [t for t, _ in leader]
    assert State.RESHAPE in targets
    first_reverse = targets.index(State.DEADLOCK_REVERSE)
    assert State.RESHAPE in targets[:first_reverse]
    assert targets[-1] == State.ARRIVED
    assert not log.collisions
    _backed_out_within_the_papers_bounds(log)


@pytest.mark.slow
def test_the_chain_gets_past_the_dead_end_backing_out_at_most_once() -> None:
    # At the U's mouth the sonar's arcs close the mouth on the map and open it again
    # from one re-plan to the next, so the chain's route flips between going in and
    # going round: a route leading back for a single re-plan declared a dead end at the
    # mouth, three times, and the chain never got round. Only a route that leads back
    # two re-plans running does now. The chain's third robot trails the second, so
    # its leader turns as fast as the second robot's slot allows: it now takes the way
    # round while the route offers it (102 s, no reverse), where it used to drive in
    # and back out (264 s). Either way it gets there, in formation when backing out.
    log = run_batch(load_scenario(SCENARIOS / "nav_deadend_inline3.toml"))
    leader = [e.target for e in log.transitions["r1"]]
    assert leader.count(State.DEADLOCK_REVERSE) <= 1
    assert leader[-1] == State.ARRIVED
    assert not log.collisions
    if State.DEADLOCK_REVERSE in leader:
        _backed_out_within_the_papers_bounds(log)


@pytest.mark.slow
@pytest.mark.parametrize("shape", ["wedge", "collateral"])
def test_a_column_turned_round_in_the_dead_end_drives_out_round_the_wall(shape: str) -> None:
    # The wedge and the line abreast of five fold into a column, which turns round inside
    # the U and drives out along its wall. At the mouth the wedge's route turns back round
    # the wall's end: behind the leader, but not the way it came. That was called a dead
    # end, and the group backed into the U again twice (at the goal after 430 s, past the
    # scenario's 360 s). The line abreast's followers, driving along the U's wall, looked
    # at it past each other, and the beams that met a robot wore the wall off the map:
    # its route led out through it, a dead end was called, and it ran out of the 360 s.
    # A dead end may be called deep inside the U, where the column cannot turn round as a
    # rigid body (the wedge's reverse then stops at the U's wall, and it turns round).
    log = run_batch(load_scenario(SCENARIOS / f"nav_deadend_{shape}5.toml"))
    leader = [e.target for e in log.transitions["r1"]]
    assert leader[-1] == State.ARRIVED
    assert not log.collisions
    trace = log.traces["r1"]
    reversing = [k for k, state in enumerate(trace.states) if state == State.DEADLOCK_REVERSE]
    assert all(trace.pose(k).x_m > U_MOUTH_X_M + 2.0 for k in reversing)


@pytest.mark.slow
def test_a_group_caught_turning_turns_back_before_it_backs_out() -> None:
    # The wedge of three (kept in its shape) is turning on the spot at the end
    # of the U when the deadlock is declared (31 deg off the U's axis): backing out along
    # that heading would run it into the side wall.
    scenario = navigation_scenario("deadend", "wedge", 3, overrides={"navigation.reshape": False})
    runner = BatchRunner(scenario)

    def turned(b: BatchRunner) -> bool:
        return any(e.target == State.DEADLOCK_TURN for e in b.agents["r1"].transitions)

    log = runner.run(until=turned)
    assert not log.collisions
    leader = log.traces["r1"]
    states = list(leader.states)
    start = states.index(State.DEADLOCK_REVERSE)
    assert abs(math.degrees(leader.theta_rad[start])) > 10.0  # caught mid-turn
    backing = [
        k for k, s in enumerate(states) if s == State.DEADLOCK_REVERSE and leader.v_mps[k] < -0.05
    ]
    assert backing, "the group never backed out"
    headings_deg = [math.degrees(leader.theta_rad[k]) for k in backing]
    assert max(abs(h) for h in headings_deg) < 3.0  # back along the U's axis, not 12 deg off it
    reverses = [e for e in log.transitions["r1"] if e.target == State.DEADLOCK_REVERSE]
    assert len(reverses) == 1
    done = next(e for e in log.transitions["r1"] if e.source == State.DEADLOCK_REVERSE)
    assert "safe distance" in done.reason
    _, backward = phase_masks(log)
    for rid in ("r2", "r3"):  # (the followers' errors)
        series = error_series(log, rid)
        assert series.linear_pct[backward].max() < 0.5
        assert series.angular_pct[backward].max() < 0.3


def test_a_boxed_in_group_stops_for_good_and_says_why() -> None:
    walls = [
        PolygonObstacle(vertices_m=v).model_dump()
        for v in (
            ((-3.0, 2.5), (3.5, 2.5), (3.5, 2.8), (-3.0, 2.8)),
            ((-3.0, -2.8), (3.5, -2.8), (3.5, -2.5), (-3.0, -2.5)),
            ((3.2, -2.5), (3.5, -2.5), (3.5, 2.5), (3.2, 2.5)),
            ((-3.3, -2.5), (-3.0, -2.5), (-3.0, 2.5), (-3.3, 2.5)),
        )
    ]
    scenario = navigation_scenario(
        "corridor",
        "wedge",
        3,
        overrides={
            "world": {"polygons": walls},
            "duration_s": 150.0,
            "deadlock.max_retries": 1,
            "deadlock.safe_distance_m": 1.0,
            "navigation.stall_s": 5.0,
        },
    )
    log = run_batch(scenario)
    nav = navigation_metrics(log)
    assert nav["stuck"]
    assert "deadlock" in nav["stuck_reason"]
    assert "max_retries = 1" in nav["stuck_reason"]
    assert "no way to it on the map" in nav["stuck_reason"]
    assert nav["deadlock_reverses"] == 1
    assert not log.collisions
    for rid, tr in log.traces.items():
        assert tr.states[-1] == State.STUCK, rid
        assert tr.cmd_v_mps[-1] == 0.0, rid
        assert abs(tr.v_mps[-1]) < 1e-9, rid
    assert run_metrics(log)["navigation"]["stuck"]


def test_without_a_goal_the_leader_wanders_and_nobody_collides() -> None:
    scenario = navigation_scenario(
        "corridor", "wedge", 3, overrides={"navigation.waypoints": [], "duration_s": 40.0}
    )
    log = run_batch(scenario)
    assert State.WANDER in log.traces["r1"].states
    assert not log.collisions
    assert np.hypot(log.traces["r1"].x_m[-1], log.traces["r1"].y_m[-1]) > 3.0


def test_a_follower_boxed_in_on_its_detour_turns_away_from_its_slot_to_get_out() -> None:
    # Where the chain of five's field 20 left its last robot: 11 cm from a post ahead and
    # to its right, the field's wall 1.2 m to its left, its slot 1.7 m ahead past the
    # post and moving away. No way within a quarter turn of the slot is clear for the
    # whole way; it stood there (AVOID, 0 m/s) while the group went on, 96 s in that run.
    scenario = navigation_scenario(
        "field",
        "inline",
        2,
        seed=20,
        overrides={
            "robots": [
                {"id": "r1", "start": {"x_m": 10.5, "y_m": 5.3, "theta_deg": 0.0}},
                {"id": "r2", "start": {"x_m": 7.83, "y_m": 4.82, "theta_deg": 31.0}},
            ],
            "duration_s": 20.0,
            "initial_settle_s": 0.0,
        },
    )
    log = run_batch(scenario)
    boxed = log.traces["r2"]
    assert State.AVOID in boxed.states[:10]  # it starts on a detour
    out = next(e for e in log.transitions["r2"] if e.source == State.AVOID)
    assert out.target == State.FORMATION_TRACK
    assert out.t_s < 10.0
    assert math.hypot(boxed.x_m[-1] - 7.83, boxed.y_m[-1] - 4.82) > 3.0
    assert not log.collisions


def test_a_group_that_cannot_back_off_turns_to_a_free_way_not_back_to_the_blocked_one() -> None:
    # Field 5063 once: the line abreast of five, folded into a column, stood 0.45-0.5 m
    # short of a post's echo along its route's heading (an obstacle blocks at 0.5 m), the
    # column's tail against a post behind it. The reverse went nowhere, the turn towards
    # the route ended on that same heading, and the deadlock came back 0.2 s later: 16
    # reverses in 110 s. The leader's turn, as its parts are built for a run, with the
    # route straight ahead and a post's echoes on it.
    runner = BatchRunner(navigation_scenario("field", "collateral", 5, seed=5063))
    turn = runner.agents["r1"].parts.turn
    start, goal = runner.scenario.robots[0].start, turn.route.waypoints[0]
    pose = Pose2D(start.x_m, start.y_m, math.atan2(goal[1] - start.y_m, goal[0] - start.x_m))
    ys = np.linspace(-0.2, 0.2, 9)
    post = (np.full(ys.size, 0.71), ys)  # 0.45 m off the body's front
    sensing = Sensing(post, post, 0.45, {1: True, -1: True}, False, False, False)
    view = FleetView({}, None, True, "r1", None, None)
    turn.enter(Moment(10.0, State.DEADLOCK_TURN, Odometry(pose, ZERO_TWIST, 10.0), sensing, view))
    end_rad = turn.side * turn.target_rad
    assert abs(end_rad) > math.radians(10.0)  # not back onto the route's heading
    room_m = TURN_ROOM * turn.deadlock.obstacle_range_m
    assert clearance_along(post, end_rad, half_width_m=turn.shape.half_width_m) >= room_m


@pytest.mark.slow
def test_a_stalled_group_folds_before_it_calls_a_deadlock() -> None:
    # Field 5028: 3.5 m in, the line abreast of three faces two posts 1.6 m apart. No
    # way is free for the whole line, so its leader turns on the spot from one heading
    # to another (-58 deg, +26 deg, -58 deg ...) and gets nowhere. That stall was a
    # deadlock: it backed off 2 m, came back and stalled again, six times, and ran out
    # of the 240 s. A stalled group now folds first, and the column goes through (once
    # past the posts, blocked 1.3 m on, the column backs off 0.4 m once, turns and
    # drives on).
    log = run_batch(navigation_scenario("field", "collateral", 3, seed=5028))
    leader = [e.target for e in log.transitions["r1"]]
    assert leader[0] == State.RESHAPE  # folded where it stalled, before any deadlock
    assert leader.count(State.DEADLOCK_REVERSE) <= 1
    assert leader[-1] == State.ARRIVED
    assert not log.collisions


@pytest.mark.slow
def test_a_wedge_of_three_rides_on_and_a_blocked_leader_folds_before_it_reverses() -> None:
    # Field 96: the wedge of three rides on in its shape (its fold is short, so the
    # sonar's squeeze does not fold it) until its leader's own way is blocked. Blocked,
    # the leader handed the lead to a follower, which was blocked in turn: eight
    # deadlock reverses by the three robots, three changes of leader, never at the goal.
    # A blocked leader now folds the group first, and the column goes through.
    log = run_batch(navigation_scenario("field", "wedge", 3, seed=96))
    nav = navigation_metrics(log)
    assert nav["deadlock_reverses"] == 0
    assert nav["leadership_changes"] == 0
    leader = [e.target for e in log.transitions["r1"]]
    assert State.RESHAPE in leader
    assert leader[-1] == State.ARRIVED
    assert not log.collisions
    assert nav["scenario_shape_share"] > 0.5  # in the wedge most of the way


def test_breadcrumbs_know_the_way_they_came_in() -> None:
    crumbs = Breadcrumbs(length_m=5.0)
    heading = math.radians(30.0)
    for k in range(31):  # 1.5 m in at 30 deg
        crumbs.drop(Vec2(0.05 * k * math.cos(heading), 0.05 * k * math.sin(heading)))
    assert crumbs.heading_in_rad(2.0) is None  # not that much path yet
    assert crumbs.heading_in_rad(1.0) == pytest.approx(heading)
    for _ in range(40):  # turning on the spot drops nothing
        crumbs.drop(Vec2(1.5 * math.cos(heading), 1.5 * math.sin(heading)))
    assert crumbs.heading_in_rad(1.0) == pytest.approx(heading)


@dataclass(frozen=True)
class GapRun:
    """The line abreast of three through its gap: the log, per step how many robots
    stood in a cell the fleet's map showed occupied, the echoes the map found to be the
    fleet's robots, and how many robots there are.
    """

    log: RunLog
    stood_on: list[int]
    robot_echoes: int
    robots: int


@pytest.fixture(scope="module")
def gap_run() -> GapRun:
    """One run for the tests of the line's fold and of its map."""
    runner = BatchRunner(load_scenario(SCENARIOS / "nav_narrow_collateral3.toml"))
    fleet = next(iter(runner.agents.values())).parts.planner.fleet
    assert fleet is not None
    stood_on: list[int] = []

    def count(b: BatchRunner) -> bool:
        row, col, _ = fleet.map.index(np.asarray(b.world.x), np.asarray(b.world.y))
        stood_on.append(int(fleet.map.occupied()[row, col].sum()))
        return False

    log = runner.run(until=count)
    return GapRun(log, stood_on, fleet.robot_echoes, len(runner.agents))


@pytest.mark.slow
def test_a_line_folds_on_the_move_to_pass_a_gap_narrower_than_itself(gap_run: GapRun) -> None:
    log = gap_run.log
    nav = navigation_metrics(log)
    assert nav["goal_reached"]
    assert not log.collisions
    leader = log.traces["r1"]
    reshaping = [k for k, s in enumerate(leader.states) if s == State.RESHAPE]
    assert nav["reshapes"] >= 2  # folded before the gap, unfolded after it
    # (the shapes go from the widest, 0, to the narrowest)
    folding = [k for k in reshaping if leader.shapes[k][1] > leader.shapes[k][0]]
    unfolding = [k for k in reshaping if leader.shapes[k][1] < leader.shapes[k][0]]
    # the group kept going while its slots slid, faster while the followers dropped back
    assert max(leader.cmd_v_mps[k] for k in folding) > 0.1 + 1e-9
    assert max(leader.cmd_v_mps[k] for k in unfolding) > 0.05
    # ... while they came up beside it, no faster than 0.1 m/s once the limiter has braked
    # to it (1 s into the unfold)
    settled = [leader.cmd_v_mps[k] for k in unfolding if k - 10 in unfolding]
    assert settled
    assert max(settled) <= 0.1 + 1e-9
    shapes = {s[1] for s in leader.shapes}
    assert shapes >= {0, 2}  # the scenario's shape and the column
    assert leader.shapes[-1][1:] == (0, 1.0)  # back in the scenario's shape at the end


@pytest.mark.slow
def test_the_fleets_map_does_not_hold_its_own_robots_as_obstacles(gap_run: GapRun) -> None:
    """The line folds and unfolds through the gap (its robots off their slots, where no
    slot mask expects them): the fleet's map seldom shows an obstacle in the cell a
    robot stands in (without leaving out the echoes of the fleet's robots: 613 of the
    7 200 robot-steps, 246 of them while the slots slide)."""
    assert navigation_metrics(gap_run.log)["goal_reached"]
    assert gap_run.robot_echoes > 0
    assert sum(gap_run.stood_on) < 0.01 * len(gap_run.stood_on) * gap_run.robots
