"""Simulated positioning sensors: odometry errors, motion capture, the marker camera."""

from __future__ import annotations

import math

import numpy as np
import pytest

from phalanx.core.config import CircleObstacle, NoiseConfig, SensorEvent, WorldConfig
from phalanx.core.config_files import load_robot
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.localisation import (
    LocalisationConfig,
    MarkerSource,
    MocapSource,
    OdometryErrors,
)
from phalanx.simulator.world import World

ROBOT = load_robot("p3dx")


def _world(
    localisation: LocalisationConfig,
    poses: dict[str, Pose2D],
    *,
    mounts: dict[str, float] | None = None,
    world: WorldConfig | None = None,
    events: tuple[SensorEvent, ...] = (),
) -> World:
    sim = World(
        robot=ROBOT, world=world or WorldConfig(), noise=NoiseConfig(), events=events, seed=4,
        localisation=localisation, mounts_rad=mounts or {},
    )  # fmt: skip
    for rid, pose in poses.items():
        sim.add_robot(rid, pose)
    return sim


def _run(world: World, commands: dict[str, Twist2D], seconds: float) -> None:
    for _ in range(round(seconds / 0.1)):
        world.step(commands, 0.1)


def test_without_errors_the_odometry_is_the_truth() -> None:
    loc = LocalisationConfig(estimator=True, mocap=MocapSource())
    world = _world(loc, {"a": Pose2D(1.0, 2.0, 0.3)})
    _run(world, {"a": Twist2D(0.2, 0.3)}, 20.0)
    truth, _ = world.truth("a")
    assert world.odometry("a").pose == truth


def test_odometry_drifts_with_its_wheel_errors() -> None:
    errors = OdometryErrors(scale_std_frac=0.01, walk_std_m=0.005, slip_per_m=0.5)
    world = _world(LocalisationConfig(estimator=True, odometry=errors), {"a": Pose2D(0, 0, 0)})
    _run(world, {"a": Twist2D(0.3, 0.1)}, 60.0)
    truth, _ = world.truth("a")
    odo = world.odometry("a").pose
    assert 0.01 < math.hypot(odo.x_m - truth.x_m, odo.y_m - truth.y_m) < 2.0


def test_motion_capture_rate_latency_noise_and_dropouts() -> None:
    source = MocapSource(rate_hz=100.0, latency_s=0.02, std_m=0.002, std_deg=0.1, dropout=0.1)
    world = _world(LocalisationConfig(estimator=True, mocap=source), {"a": Pose2D(0, 0, 0)})
    fixes = []
    for _ in range(100):  # 10 s standing still
        world.step({"a": Twist2D(0.0, 0.0)}, 0.1)
        got, _ = world.positioning("a")
        assert all(f.stamp_s + 0.02 <= world.t_s + 1e-9 for f in got)  # none before its time
        fixes += got
    assert 0.85 * 1000 < len(fixes) < 0.95 * 1000  # 100 Hz, 10 % lost
    xs = np.array([f.x_m for f in fixes])
    assert xs.std() == pytest.approx(0.002, rel=0.15)
    assert np.degrees(np.std([f.theta_rad for f in fixes])) == pytest.approx(0.1, rel=0.15)
    assert world.t_s - fixes[-1].stamp_s == pytest.approx(0.02, abs=0.011)


def _camera_world(**kwargs: object) -> World:
    markers = MarkerSource(max_range_m=4.0, fov_deg=90.0)
    loc = LocalisationConfig(estimator=True, markers=markers)
    poses = kwargs.pop("poses", {"f": Pose2D(0, 0, 0), "l": Pose2D(1.0, 0, 0.2)})
    return _world(loc, poses, mounts={"f": 0.0}, **kwargs)  # type: ignore[arg-type]


def _seen(world: World, seconds: float = 1.0) -> list[str]:
    out = []
    for _ in range(round(seconds / 0.1)):
        world.step({}, 0.1)
        out += [r.target_id for r in world.positioning("f")[1]]
    return out


def test_the_camera_sees_the_robot_ahead_with_its_noise() -> None:
    world = _camera_world()
    seen = []
    for _ in range(100):
        world.step({}, 0.1)
        seen += world.positioning("f")[1]
    assert 140 <= len(seen) <= 151  # 15 Hz over 10 s, the last ones still in flight
    assert {r.target_id for r in seen} == {"l"}
    assert np.mean([r.range_m for r in seen]) == pytest.approx(1.0, abs=0.01)
    assert np.std([r.range_m for r in seen]) == pytest.approx(0.02, rel=0.3)
    assert np.mean([r.heading_rad for r in seen]) == pytest.approx(0.2, abs=0.01)  # type: ignore[arg-type]
    assert np.degrees(np.std([r.bearing_rad for r in seen])) == pytest.approx(1.0, rel=0.3)


@pytest.mark.parametrize(
    ("leader", "why"),
    [(Pose2D(0.0, 1.5, 0.0), "outside the field of view"), (Pose2D(6.0, 0.0, 0.0), "too far")],
)
def test_the_camera_misses_what_it_cannot_see(leader: Pose2D, why: str) -> None:
    world = _camera_world(poses={"f": Pose2D(0, 0, 0), "l": leader})
    assert _seen(world) == [], why


def test_robots_and_obstacles_occlude_the_marker() -> None:
    blocker = {"f": Pose2D(0, 0, 0), "b": Pose2D(1.0, 0.05, 0.0), "l": Pose2D(2.0, 0, 0)}
    assert set(_seen(_camera_world(poses=blocker))) == {"b"}
    pillar = WorldConfig(circles=(CircleObstacle(x_m=1.0, y_m=0.0, radius_m=0.1),))
    assert _seen(_camera_world(world=pillar)) == []


def test_a_hidden_marker_gives_nothing_for_the_event() -> None:
    hide = (SensorEvent(kind="markers_hidden", start_s=0.0, duration_s=0.5, robots=("f",)),)
    world = _camera_world(events=hide)
    assert _seen(world, 0.5) == []
    assert "l" in _seen(world, 1.0)
