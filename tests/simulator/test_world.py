"""The simulated world: kinematics, limits, sonar, collisions, events, noise."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from phalanx.core.config import (
    CircleObstacle,
    NoiseConfig,
    PolygonObstacle,
    SensorEvent,
    WorldConfig,
)
from phalanx.core.config_files import load_robot
from phalanx.core.geometry import Pose2D, Twist2D, integrate_unicycle
from phalanx.simulator.world import World

ROBOT = load_robot("p3dx")
WALL_AHEAD = PolygonObstacle(vertices_m=((2.0, -3.0), (2.5, -3.0), (2.5, 3.0), (2.0, 3.0)))


def _world(**kwargs: object) -> World:
    world = World(
        robot=ROBOT,
        world=kwargs.pop("world", WorldConfig()),  # type: ignore[arg-type]
        noise=kwargs.pop("noise", NoiseConfig()),  # type: ignore[arg-type]
        events=kwargs.pop("events", ()),  # type: ignore[arg-type]
        seed=1,
    )
    world.add_robot("a", Pose2D(0.0, 0.0, 0.0))
    return world


def _drive(world: World, twist: Twist2D, seconds: float, dt_s: float = 0.1) -> None:
    for _ in range(round(seconds / dt_s)):
        world.step({"a": twist}, dt_s)


def test_circle_closes_after_one_turn_exact_arcs() -> None:
    world = _world()
    twist = Twist2D(0.2, math.radians(20.0))
    _drive(world, twist, 3.0)  # reach the commanded twist first
    start, _ = world.truth("a")
    _drive(world, twist, 18.0)  # 360 deg at 20 deg/s
    end, measured = world.truth("a")
    assert measured == Twist2D(pytest.approx(0.2), pytest.approx(math.radians(20.0)))
    assert math.hypot(end.x_m - start.x_m, end.y_m - start.y_m) < 1e-9


def test_acceleration_limit_ramps_speed() -> None:
    world = _world()
    world.step({"a": Twist2D(1.0, 0.0)}, 1.0)
    _, twist = world.truth("a")
    assert twist.v_mps == pytest.approx(ROBOT.accel_mps2 * 1.0)
    _drive(world, Twist2D(5.0, 0.0), 10.0)
    assert world.truth("a")[1].v_mps == pytest.approx(ROBOT.v_max_mps)


def test_front_sonars_see_a_wall_and_max_range_elsewhere() -> None:
    world = _world(world=WorldConfig(polygons=(WALL_AHEAD,)))
    ranges = world.status("a").sonar_ranges_m
    assert len(ranges) == 16
    # sonars 3 and 4 face +-10 deg from (0.166, +-0.027): the wall is 2 m ahead
    for i in (3, 4):
        assert ranges[i] == pytest.approx(2.0 - 0.166, abs=0.02)
    assert ranges[11] == ROBOT.sonar.max_range_m  # rear sonar: nothing behind
    rays = world.sonar_rays("a")
    assert len(rays) == 16
    assert rays[3][1].x_m == pytest.approx(2.0, abs=0.05)


def test_sonar_sees_other_robots() -> None:
    world = _world()
    world.add_robot("b", Pose2D(1.5, 0.0, 0.0))
    ranges = world.status("a").sonar_ranges_m
    assert ranges[3] == pytest.approx(1.5 - ROBOT.radius_m - 0.166, abs=0.05)


def test_beam_width_catches_an_off_axis_pole() -> None:
    pole = CircleObstacle(x_m=2.0, y_m=2.0 * math.tan(math.radians(16.0)), radius_m=0.05)
    world = _world(world=WorldConfig(circles=(pole,)))
    # 16 deg off the axis: the 10 deg sonar's beam (+-7.5 deg) reaches it
    assert world.status("a").sonar_ranges_m[3] < 2.5


def test_collision_recorded_once_and_robot_stopped() -> None:
    world = _world(world=WorldConfig(polygons=(WALL_AHEAD,)))
    _drive(world, Twist2D(0.3, 0.0), 15.0)
    pose, twist = world.truth("a")
    assert len(world.collisions) == 1
    assert world.collisions[0].other == "obstacle:0"
    assert pose.x_m < 2.0 - ROBOT.radius_m + 0.01
    assert twist.v_mps == 0.0
    assert world.status("a").bumpers == (True,)


def test_robot_robot_collision() -> None:
    world = _world()
    world.add_robot("b", Pose2D(1.0, 0.0, math.pi))
    for _ in range(40):
        world.step({"a": Twist2D(0.3, 0.0), "b": Twist2D(0.3, 0.0)}, 0.1)
    others = {(c.robot_id, c.other) for c in world.collisions}
    assert others == {("a", "b"), ("b", "a")}


def test_event_overrides_sonar_in_its_window_only() -> None:
    event = SensorEvent(start_s=1.0, duration_s=0.5, range_m=0.3)
    world = _world(events=(event,))
    seen = []
    for _ in range(20):
        seen.append(world.status("a").sonar_ranges_m[0])
        world.step({"a": Twist2D(0.0, 0.0)}, 0.1)
    blocked = [i for i, r in enumerate(seen) if r == pytest.approx(0.3)]
    assert blocked == [10, 11, 12, 13, 14]


def test_noise_is_seeded_and_zero_noise_is_exact() -> None:
    noisy = NoiseConfig(odometry_v_std_frac=0.05, odometry_omega_std_radps=0.05, sonar_std_m=0.05)
    a, b, exact = _world(noise=noisy), _world(noise=noisy), _world()
    for w in (a, b, exact):
        _drive(w, Twist2D(0.3, 0.1), 5.0)
    assert a.odometry("a").pose == b.odometry("a").pose
    assert a.odometry("a").pose != a.truth("a")[0]
    assert exact.odometry("a").pose == exact.truth("a")[0]
    assert a.status("a").sonar_ranges_m == b.status("a").sonar_ranges_m


def test_truth_matches_unicycle_integration() -> None:
    world = _world()
    _drive(world, Twist2D(0.2, 0.3), 5.0)
    pose, twist = world.truth("a")
    expected = integrate_unicycle(pose, twist, 1.0)
    world.step({"a": Twist2D(0.2, 0.3)}, 1.0)
    assert world.truth("a")[0] == Pose2D(
        pytest.approx(expected.x_m), pytest.approx(expected.y_m), pytest.approx(expected.theta_rad)
    )


@settings(max_examples=25, deadline=None)
@given(st.floats(-0.3, 0.3), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0))
def test_never_ends_inside_an_obstacle(v: float, w: float, y0: float) -> None:
    pole = CircleObstacle(x_m=1.0, y_m=0.0, radius_m=0.4)
    world = World(
        robot=ROBOT, world=WorldConfig(circles=(pole,), polygons=(WALL_AHEAD,)), noise=NoiseConfig()
    )
    world.add_robot("a", Pose2D(-0.5, y0, 0.0))
    for _ in range(100):
        world.step({"a": Twist2D(v if v > 0 else 0.3, w)}, 0.1)
        pose, _ = world.truth("a")
        assert math.hypot(pose.x_m - 1.0, pose.y_m) >= 0.4 + ROBOT.radius_m - 1e-9
        assert pose.x_m <= 2.0 - ROBOT.radius_m + 1e-9 or not (-3.0 < pose.y_m < 3.0)
    assert np.isfinite(world.x).all()


def test_a_late_firmware_acts_on_commands_and_reports_its_sonar_late() -> None:
    """`world.command_delay_s` and `sonar_delay_s` (AMRISim's P3DX: about 0.1 s and 0.2 s):
    a robot starts on a command a tick late, and its sonar tells where it was two ticks
    ago."""
    from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_scenario

    base = apply_overrides(  # r1 1 m short of the scenario's wall
        load_scenario(CONFIG_ROOT / "scenarios" / "paper_collateral.toml"),
        ["robots.0.start.x_m=11.0", "robots.0.start.y_m=5.73"], source="test",
    )  # fmt: skip
    late = apply_overrides(
        base, ["world.command_delay_s=0.1", "world.sonar_delay_s=0.2"], source="test"
    )
    ideal, firmware = World.for_scenario(base, ROBOT), World.for_scenario(late, ROBOT)
    ahead = []
    for world in (ideal, firmware):
        for _ in range(3):  # r1 towards the wall
            world.sense_all()
            world.step({"r1": Twist2D(0.3, 0.0)}, 0.1)
        ahead.append(world.status("r1").sonar_ranges_m[3])
    assert ideal.truth("r1")[0].x_m > firmware.truth("r1")[0].x_m + 0.005  # one tick less
    assert ahead[1] > ahead[0]  # an older reading: further from the wall
