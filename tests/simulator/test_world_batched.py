"""What the world and the batch runner do for every robot at once gives each robot the
numbers it would get alone: kinematics in plain floats against numpy, every sonar ring
cast in one pass against a brute-force cast robot by robot, and a fleet whose sonar is
read and masked in one pass against the same fleet reading its own.
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from plain_rays import ray_segment_hits

from phalanx.agents.agent import Observation
from phalanx.core.config import CircleObstacle, NoiseConfig, PolygonObstacle, WorldConfig
from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
from phalanx.core.geometry import Pose2D
from phalanx.core.peers import PeerState
from phalanx.core.scenarios import grid_scenario
from phalanx.runtime.batch import BatchRunner
from phalanx.simulator.kinematics import (
    apply_robot_limits,
    integrate_arcs,
    limits_and_arcs_scalar,
)
from phalanx.simulator.sonar import ray_circle_hits
from phalanx.simulator.world import World

ROBOT = load_robot("p3dx")
speeds = st.floats(-1.5, 1.5, allow_nan=False) | st.sampled_from([0.0, -0.0, 1e-10, -1e-10])


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(speeds, speeds, speeds, speeds), min_size=1, max_size=6))
def test_scalar_kinematics_are_numpys_to_the_bit(rows: list[tuple[float, ...]]) -> None:
    v, w, v_cmd, w_cmd = (np.array(c, dtype=np.float64) for c in zip(*rows, strict=True))
    rng = np.random.default_rng(len(rows))
    x, y, th = rng.normal(size=(3, len(rows))) * 5.0
    dt_s = 0.025
    v_np, w_np = apply_robot_limits(v, w, v_cmd, w_cmd, ROBOT, dt_s)
    x_np, y_np, th_np = integrate_arcs(x, y, th, v_np, w_np, dt_s)
    scalar = limits_and_arcs_scalar((x, y, th, v, w, v_cmd, w_cmd), ROBOT, dt_s)
    for ours, theirs in zip(scalar, (v_np, w_np, x_np, y_np, th_np), strict=True):
        assert ours.tobytes() == theirs.tobytes()


def _fleet(n: int, *, noise: float = 0.0) -> World:
    world = World(
        robot=ROBOT,
        world=WorldConfig(
            circles=tuple(CircleObstacle(x_m=x, y_m=3.0, radius_m=0.4) for x in range(-9, 9, 3)),
            polygons=(
                PolygonObstacle(vertices_m=((6.0, -9.0), (7.0, -9.0), (7.0, 2.0), (6.0, 2.0))),
            ),
        ),
        noise=NoiseConfig(sonar_std_m=noise),
        seed=3,
    )
    rng = np.random.default_rng(n)
    cols = math.ceil(math.sqrt(n))
    for i in range(n):
        x, y = -(i // cols) * 1.3 + rng.uniform(-0.2, 0.2), -(i % cols) * 1.3
        world.add_robot(f"g{i}", Pose2D(x, y, rng.uniform(-math.pi, math.pi)))
    return world


def _brute_force(world: World, i: int) -> np.ndarray:
    """One robot's ranges: every ray against every circle, robot and edge (no pruning)."""
    ring = world.ring
    c, s = math.cos(world.th[i]), math.sin(world.th[i])
    ox = world.x[i] + c * ring.origin_x - s * ring.origin_y
    oy = world.y[i] + s * ring.origin_x + c * ring.origin_y
    ang = world.th[i] + ring.angle_rad
    dx, dy = np.cos(ang), np.sin(ang)
    near = np.hypot(world.x - world.x[i], world.y - world.y[i]) < ring.max_range_m + 0.76
    near[i] = False
    circles = world._circles
    cx = np.concatenate([circles[:, 0], world.x[near]])
    cy = np.concatenate([circles[:, 1], world.y[near]])
    r = np.concatenate([circles[:, 2], np.full(int(near.sum()), world.robot.radius_m)])
    hits = ray_circle_hits(ox, oy, dx, dy, cx, cy, r)
    e = world._edges
    hits = np.minimum(hits, ray_segment_hits(ox, oy, dx, dy, e.ax, e.ay, e.bx, e.by))
    per_unit = np.full(ring.units, np.inf)
    np.minimum.at(per_unit, ring.unit_of_ray, hits)
    return np.clip(per_unit, ring.min_range_m, ring.max_range_m)


def test_one_pass_cast_is_the_brute_force_cast_robot_by_robot() -> None:
    for n in (3, 90):  # a pairwise broad phase, and the grid's
        world = _fleet(n)
        ranges = world.sense_all()
        assert (ranges < world.ring.max_range_m).any()
        for i in range(n):
            assert ranges[i].tobytes() == _brute_force(world, i).tobytes()


def test_one_pass_cast_draws_the_same_noise_as_robot_by_robot() -> None:
    together, alone = _fleet(12, noise=0.02), _fleet(12, noise=0.02)
    ranges = together.sense_all()
    for i, rid in enumerate(alone.robot_ids):
        assert np.array(alone.status(rid).sonar_ranges_m).tobytes() == ranges[i].tobytes()


class _AloneRunner(BatchRunner):
    """Every agent reads and masks its own sonar, as it does in its own process."""

    def _observe(self, peers: dict[str, PeerState], t_s: float) -> list[tuple]:  # type: ignore[override]
        odometry = self.world.odometries()
        statuses, _ = self.world.statuses()
        return [
            (rid, agent, Observation(odometry[i], statuses[i]))
            for i, (rid, agent) in enumerate(self.agents.items())
        ]


def test_fleet_sensing_in_one_pass_is_each_robots_own() -> None:
    base = load_scenario(CONFIG_ROOT / "scenarios" / "paper_wedge.toml")
    scenario = grid_scenario(base, 20, duration_s=8.0)
    one_pass, alone = BatchRunner(scenario).run(), _AloneRunner(scenario).run()
    for rid, trace in one_pass.traces.items():
        other = alone.traces[rid]
        for name in ("x_m", "y_m", "theta_rad", "v_mps", "omega_radps", "cmd_v_mps"):
            assert getattr(trace, name).tobytes() == getattr(other, name).tobytes(), (rid, name)
        assert trace.states == other.states
