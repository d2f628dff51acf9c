"""A world step in which no contact can begin or end runs its sub-steps without contact
checks (`World._glide`): the same numbers, to the bit, as the sub-step-by-sub-step path,
and never a contact missed. And a batch run keeps what it built out of the garbage
collector's full passes while it runs.
"""

from __future__ import annotations

import gc
import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from phalanx.core.config import CircleObstacle, NoiseConfig, PolygonObstacle, WorldConfig
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.runtime.batch import BatchRunner
from phalanx.simulator.contacts import Contacts, polygon_edges
from phalanx.simulator.kinematics import limits_and_arcs_scalar
from phalanx.simulator.world import World

ROBOT = load_robot("p3dx")
speeds = st.floats(-1.5, 1.5, allow_nan=False) | st.sampled_from([0.0, -0.0, 1e-10, -1e-10])


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(speeds, speeds, speeds, speeds), min_size=1, max_size=6))
def test_scalar_sub_steps_in_a_row_are_sub_steps_one_by_one(rows: list[tuple[float, ...]]) -> None:
    v, w, v_cmd, w_cmd = (np.array(c, dtype=np.float64) for c in zip(*rows, strict=True))
    x, y, th = np.random.default_rng(len(rows)).normal(size=(3, len(rows))) * 5.0
    one = (x, y, th, v, w)
    for _ in range(4):
        vv, ww, xx, yy, tt = limits_and_arcs_scalar((*one, v_cmd, w_cmd), ROBOT, 0.025)
        one = (xx, yy, tt, vv, ww)
    four = limits_and_arcs_scalar((x, y, th, v, w, v_cmd, w_cmd), ROBOT, 0.025, substeps=4)
    for ours, theirs in zip(four, (one[3], one[4], one[0], one[1], one[2]), strict=True):
        assert ours.tobytes() == theirs.tobytes()


def _world(n: int) -> World:
    circles = tuple(CircleObstacle(x_m=x, y_m=y, radius_m=0.4) for x in (1.2, 2.5) for y in (0, 2))
    world = World(robot=ROBOT, world=WorldConfig(circles=circles), noise=NoiseConfig(), seed=1)
    cols = math.ceil(math.sqrt(n))
    for i in range(n):
        world.add_robot(f"g{i}", Pose2D(-(i // cols) * 1.0, -(i % cols) * 1.0 + 1.5, 0.1 * i))
    return world


def _drive(world: World, *, glide: bool) -> tuple[int, int]:
    """120 ticks of commands driving the fleet into the circles and into each other:
    (ticks that glided, ticks that did not).
    """
    rng = np.random.default_rng(7)
    glided = checked = 0
    for _ in range(120):
        commands = {
            rid: Twist2D(float(rng.uniform(0.2, 0.9)), float(rng.uniform(-1.0, 1.0)))
            for rid in world.robot_ids
        }
        free = glide and world._contact_free(0.1)
        glided, checked = glided + free, checked + (not free)
        if not glide:
            world._contact_free = lambda dt_s: False  # type: ignore[method-assign]
        world.step(commands, 0.1)
    return glided, checked


def test_a_contact_free_step_is_the_sub_step_by_sub_step_one() -> None:
    for n in (5, 20):  # plain floats and numpy
        fast, slow = _world(n), _world(n)
        glided, checked = _drive(fast, glide=True)
        _drive(slow, glide=False)
        assert glided  # both paths taken
        assert checked
        for name in ("x", "y", "th", "v", "w", "odo", "bumped"):
            assert getattr(fast, name).tobytes() == getattr(slow, name).tobytes(), name
        assert fast.collisions == slow.collisions
        assert fast.collisions  # robots did run into the circles and each other


def test_no_contact_can_begin_within_the_travel_checked() -> None:
    world = WorldConfig(circles=(CircleObstacle(x_m=2.0, y_m=0.0, radius_m=0.5),))
    contacts = Contacts(world, np.array([[2.0, 0.0, 0.5]]), polygon_edges(world), ["a", "b"])
    x, y = np.array([0.0, -3.0]), np.array([0.0, 0.0])
    gap_m = 2.0 - 0.5 - ROBOT.radius_m  # robot a to the circle
    assert contacts.none_within(x, y, ROBOT.radius_m, 0.99 * gap_m)
    assert not contacts.none_within(x, y, ROBOT.radius_m, gap_m)
    pair_gap_m = 3.0 - 2 * ROBOT.radius_m  # a to b: both may close it
    far = np.array([-10.0, -10.0 - 3.0]), np.array([0.0, 0.0])
    assert contacts.none_within(*far, ROBOT.radius_m, 0.49 * pair_gap_m)
    assert not contacts.none_within(*far, ROBOT.radius_m, 0.5 * pair_gap_m)
    contacts.under_way.add(("a", "obstacle:0"))  # a contact to release: checked each sub-step
    assert not contacts.none_within(*far, ROBOT.radius_m, 0.0)
    triangle = PolygonObstacle(vertices_m=((9.0, 9.0), (10.0, 9.0), (10.0, 10.0)))
    walls = WorldConfig(polygons=(triangle,))
    polygons = Contacts(walls, np.zeros((0, 3)), polygon_edges(walls), ["a", "b"])
    assert polygons.none_within(*far, ROBOT.radius_m, 0.0)
    # the triangle's bounding box, not the triangle, is kept clear of
    x, y = np.array([9.0, -10.0]), np.array([10.0 + ROBOT.radius_m + 0.2, 0.0])
    assert polygons.none_within(x, y, ROBOT.radius_m, 0.19)
    assert not polygons.none_within(x, y, ROBOT.radius_m, 0.2)
    assert polygons.near_walls(x, y, ROBOT.radius_m, 0.2) == [0]
    inside = np.array([9.9, -10.0]), np.array([9.1, 0.0])  # robot a within the triangle
    assert not polygons.none_within(*inside, ROBOT.radius_m, 0.0)


def test_a_batch_run_keeps_its_fleet_out_of_full_collections_and_gives_it_back() -> None:
    scenario = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
    frozen_during: list[int] = []

    def until(runner: BatchRunner) -> bool:
        frozen_during.append(gc.get_freeze_count())
        return runner.done >= 3

    BatchRunner(scenario).run(until=until)
    assert min(frozen_during) > 0  # the fleet built before the run: frozen meanwhile
    assert gc.get_freeze_count() == 0  # and collectable again after it
