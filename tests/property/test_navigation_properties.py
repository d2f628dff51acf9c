"""Property tests of the navigation and leadership math (hypothesis)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from phalanx.agents.leadership import Leadership, LiveFlags, newer
from phalanx.agents.navigation import (
    HEADINGS_RAD,
    Clearances,
    clearance_along,
    corridor_clearance,
    free_heading_near,
    heading_index,
    steer,
)
from phalanx.agents.navigation.steering import NEAR_NEED_M, choose_heading
from phalanx.agents.perception import SonarGeometry
from phalanx.agents.shape import TAIL_SHARE, TURN_CENTRE_MARGIN_M, Shape
from phalanx.core.config import FormationConfig, LeadershipConfig, NavigationConfig, SlotConfig
from phalanx.core.config_files import load_robot
from phalanx.core.formation import Formation, resolve_formation
from phalanx.core.geometry import Vec2
from phalanx.core.limits import KinematicLimits
from phalanx.wire.messages import RobotFlags

SONAR = SonarGeometry.from_params(load_robot("p3dx"))


@st.composite
def trees(draw: st.DrawFn) -> Formation:
    """A random follow tree of 2-8 robots, slots at random bearings."""
    n = draw(st.integers(2, 8))
    slots = [SlotConfig(robot="r1", x_m=0.0, y_m=0.0)]
    for i in range(2, n + 1):
        parent = draw(st.integers(1, i - 1))
        phi = draw(st.floats(0.0, 359.0))
        slots.append(SlotConfig(robot=f"r{i}", follows=f"r{parent}", l_m=1.0, phi_deg=phi))
    return resolve_formation(FormationConfig(slots=tuple(slots)))


@settings(max_examples=60, deadline=None)
@given(trees(), st.data())
def test_rerooting_gives_a_tree_of_neighbours(formation: Formation, data: st.DataObject) -> None:
    leader = data.draw(st.sampled_from(formation.robot_ids))
    parents = formation.reroot(leader)
    assert [r for r, p in parents.items() if p is None] == [leader]
    for robot, parent in parents.items():
        if parent is not None:
            assert parent in formation.neighbours(robot)  # still a neighbour it tracks
        hops, at = 0, robot
        while at != leader:  # every chain ends at the leader: no cycle
            at = parents[at]  # type: ignore[assignment]
            hops += 1
            assert hops < len(parents)


@settings(max_examples=60, deadline=None)
@given(trees(), st.data())
def test_slots_compose_along_any_path(formation: Formation, data: st.DataObject) -> None:
    a, b, c = (data.draw(st.sampled_from(formation.robot_ids)) for _ in range(3))
    direct = formation.slot_of(a, c)
    composed = formation.slot_of(a, b) + formation.slot_of(b, c)
    assert math.isclose(direct.x_m, composed.x_m, abs_tol=1e-9)
    assert math.isclose(direct.y_m, composed.y_m, abs_tol=1e-9)


claims = st.lists(
    st.tuples(st.integers(0, 5), st.sampled_from(["r1", "r2", "r3", "r4"])), min_size=1, max_size=12
)


@settings(max_examples=80, deadline=None)
@given(claims, st.randoms())
def test_epochs_never_go_back_whatever_the_order(heard: list[tuple[int, str]], rng: object) -> None:
    """Claims heard in any order: the epoch never goes down, and the pair held is the
    start or one heard (which claims the fleet stands behind: tests/faults/
    test_leadership_claims.py)."""
    formation = resolve_formation(
        FormationConfig(
            slots=(
                SlotConfig(robot="r1", x_m=0.0, y_m=0.0),
                *(SlotConfig(robot=f"r{i}", follows="r1", l_m=1.0, phi_deg=180.0 + 20 * i)
                  for i in range(2, 5)),
            )
        )
    )  # fmt: skip
    for shuffle in range(3):
        order = list(heard)
        if shuffle:
            rng.shuffle(order)  # type: ignore[attr-defined]
        view = Leadership("r4", formation, LeadershipConfig(handover=False), timeout_s=1e9)
        epochs = [view.epoch]
        for epoch, leader in order:
            message = RobotFlags(
                robot_id="r2", seq=0, stamp_s=0.0, fsm_state="FORMATION_TRACK",
                formation_leader_id=leader, epoch=epoch,
            )  # fmt: skip
            view.update(
                {"r2": message, leader: message.model_copy(update={"robot_id": leader})}, 0.0
            )
            epochs.append(view.epoch)
        assert epochs == sorted(epochs)
        assert (view.epoch, view.leader_id) in {(0, "r1"), *heard}


points = st.lists(st.tuples(st.floats(-4, 4), st.floats(-4, 4)), min_size=1, max_size=30)


@settings(max_examples=60, deadline=None)
@given(points, st.floats(0.1, 0.6), st.floats(0.0, 0.4))
def test_a_wider_corridor_is_never_freer(
    xy: list[tuple[float, float]], w: float, dw: float
) -> None:
    p = (np.array([a for a, _ in xy]), np.array([b for _, b in xy]))
    narrow = corridor_clearance(p, HEADINGS_RAD, half_width_m=w)
    wide = corridor_clearance(p, HEADINGS_RAD, half_width_m=w + dw)
    assert np.all(wide <= narrow + 1e-9)
    assert np.all(narrow >= 0.0)


@settings(max_examples=60, deadline=None)
@given(points, st.floats(-math.pi, math.pi), st.floats(0.3, math.pi))
def test_the_chosen_heading_lies_within_the_window(
    xy: list[tuple[float, float]], desired: float, window: float
) -> None:
    p = (np.array([a for a, _ in xy]), np.array([b for _, b in xy]))
    clear = corridor_clearance(p, HEADINGS_RAD, half_width_m=0.3)
    index = choose_heading(desired, wide=clear, narrow=clear, need_m=2.0, window_rad=window)
    off = abs((HEADINGS_RAD[index] - desired + math.pi) % (2 * math.pi) - math.pi)
    step = float(HEADINGS_RAD[1] - HEADINGS_RAD[0])
    assert off <= max(window, step / 2) + 1e-9
    offs = np.abs((HEADINGS_RAD - desired + math.pi) % (2 * math.pi) - math.pi)
    need = np.minimum(2.0, NEAR_NEED_M + (2.0 - NEAR_NEED_M) * offs / window)
    if ((clear >= need) & (offs <= window)).any():  # a way exists: the choice is one of them
        assert clear[index] >= need[index] - 1e-9


@settings(max_examples=80, deadline=None)
@given(points, st.floats(-math.pi, math.pi), st.floats(0.1, 3.0))
def test_a_deadlocks_turn_ends_on_the_free_heading_nearest_the_route(
    xy: list[tuple[float, float]], route: float, room: float
) -> None:
    p = (np.array([a for a, _ in xy]), np.array([b for _, b in xy]))
    chosen = free_heading_near(p, route, half_width_m=0.3, room_m=room)
    if clearance_along(p, route, half_width_m=0.3) >= room:
        assert chosen == route  # the route's own heading is free: nothing changes
        return
    clear = corridor_clearance(p, HEADINGS_RAD, half_width_m=0.3)
    offs = np.abs((HEADINGS_RAD - route + math.pi) % (2 * math.pi) - math.pi)
    if not (clear >= room).any():
        assert chosen == route  # nowhere free: the route it is
        return
    at = heading_index(chosen)
    assert HEADINGS_RAD[at] == chosen  # one of the candidate headings
    off = abs((chosen - route + math.pi) % (2 * math.pi) - math.pi)
    assert clear[at] >= room
    assert off <= offs[clear >= room].min() + 1e-12  # no free heading lies nearer the route


@settings(max_examples=80, deadline=None)
@given(trees(), st.data())
def test_newest_claim_is_the_one_a_fold_of_newer_adopts(
    formation: Formation, data: st.DataObject
) -> None:
    """`LiveFlags.newest`, worked out once for the whole group, picks what folding rule 1
    over every robot's flags from any robot's own view would."""
    ids = list(formation.robot_ids)
    claims = {
        r: RobotFlags(
            robot_id=r,
            seq=1,
            stamp_s=1.0,
            fsm_state="FORMATION_TRACK",
            epoch=data.draw(st.integers(0, 3)),
            formation_leader_id=data.draw(st.sampled_from([*ids, "stranger"])),
        )
        for r in ids
    }
    live = LiveFlags(claims, formation)
    mine = (data.draw(st.integers(0, 3)), data.draw(st.sampled_from(ids)))
    folded = mine
    for f in claims.values():
        if newer((f.epoch, f.formation_leader_id), folded, formation):
            folded = (f.epoch, f.formation_leader_id)
    adopted = live.newest if live.newest and newer(live.newest, mine, formation) else mine
    assert adopted == folded


@settings(max_examples=150, deadline=None)
@given(st.lists(st.floats(0.2, 5.5), min_size=16, max_size=16), st.data())
def test_echoes_of_known_robots_match_the_disc_by_disc_test(
    ranges: list[float], data: st.DataObject
) -> None:
    """Dropping far discs before the vectorised test changes nothing: every echo is kept
    or dropped exactly as testing each disc on its own would. Discs sit anywhere, and
    near some echo's arc (where a wrong cut-off would show)."""
    r = np.clip(np.array(ranges), 0.0, SONAR.max_range_m)
    known = []
    for _ in range(data.draw(st.integers(0, 6))):
        k = data.draw(st.integers(0, 15))
        along = float(r[k]) + data.draw(st.floats(-0.7, 0.7))
        bearing = float(SONAR.unit_heading_rad[k]) + data.draw(st.floats(-0.5, 0.5))
        centre = Vec2(
            float(SONAR.unit_x_m[k]) + along * math.cos(bearing),
            float(SONAR.unit_y_m[k]) + along * math.sin(bearing),
        )
        known.append((centre, data.draw(st.floats(0.1, 0.6))))
    expected = r < SONAR.max_range_m - 1e-6
    for centre, radius_m in known:
        expected &= ~SONAR.arcs_meet(r, [(centre, radius_m)])[0]
    assert np.array_equal(SONAR.echoes(r, known), expected)


@settings(max_examples=80, deadline=None)
@given(formation=trees(), speed_mps=st.floats(0.01, 0.3), left=st.booleans())
def test_a_narrow_shape_turns_tighter_but_swings_no_slot_backwards(
    formation: Formation, speed_mps: float, left: bool
) -> None:
    """A leader may turn tighter than `min_turn_radius_m` only where the shape is narrow
    enough across its heading that every slot of the rigid shape still moves forwards
    (either way round); a shape as wide as that, or as long, keeps the configured radius.
    """
    robot = load_robot("p3dx")
    nav = NavigationConfig()
    leader = formation.robot_ids[0]
    shape = Shape(
        leader, formation, radius_m=robot.radius_m, nav=nav,
        limits=KinematicLimits.from_params(robot), dt_s=0.1,
    )  # fmt: skip
    radius_m = shape.turn_radius_m()
    assert 0.0 < radius_m <= nav.min_turn_radius_m
    across_m = max(abs(s.y_m) for s in shape.follower_slots)
    if radius_m < nav.min_turn_radius_m:
        omega = (1.0 if left else -1.0) * speed_mps / radius_m
        for slot in shape.follower_slots:
            # a rigid body's point at (x, y) moves forwards at v - omega y
            assert speed_mps - omega * slot.y_m > 0.0
    else:  # as wide as that, or long enough that its tail would sweep wide
        wide = across_m + robot.radius_m + TURN_CENTRE_MARGIN_M >= nav.min_turn_radius_m - 1e-9
        long = TAIL_SHARE * shape.reach_m >= nav.min_turn_radius_m - 1e-9
        assert wide or long


@settings(max_examples=80, deadline=None)
@given(st.floats(-0.35, 0.35), st.floats(-0.35, 0.35), st.floats(0.0, 4.0))
def test_on_an_open_floor_the_yaw_rate_follows_the_heading_wanted_smoothly(
    first: float, second: float, min_radius_m: float
) -> None:
    """No jump between straight on and a full-rate bend as the heading wanted crosses
    from one candidate heading's share to the next: the yaw rate moves by at most the
    heading gain times the change of the heading wanted.
    """
    nav = NavigationConfig()
    free = np.full(HEADINGS_RAD.shape, 10.0)

    def omega(desired: float) -> float:
        twist, _ = steer(
            desired, Clearances(free, free), nav=nav, speed_mps=0.2, stop_gap_m=0.5,
            need_m=3.0, omega_max_radps=0.7, min_radius_m=min_radius_m,
        )  # fmt: skip
        return twist.omega_radps

    assert abs(omega(first) - omega(second)) <= nav.heading_gain_per_s * abs(first - second) + 1e-9
