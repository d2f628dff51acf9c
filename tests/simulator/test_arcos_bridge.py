"""The world-moved ARCOS body: a SIP reports where the body is when it is sent."""

from __future__ import annotations

import math

import pytest

from phalanx.core.config_files import load_robot
from phalanx.core.geometry import Pose2D
from phalanx.runtime.arcos_bridge import MAX_FRAME_AGE_S, WorldBody
from phalanx.wire.messages import SenseFrame

ROBOT = load_robot("p3dx")
ORIGIN = Pose2D(1.0, 2.0, math.pi / 2)


class FakeClock:
    """A monotonic clock the test moves by hand."""

    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s


def _frame(
    x_m: float, y_m: float, theta_rad: float, v_mps: float, omega_radps: float
) -> SenseFrame:
    return SenseFrame(
        robot_id="r1", tick=0, t_s=0.0, dt_s=0.1, x_m=x_m, y_m=y_m, theta_rad=theta_rad,
        v_mps=v_mps, omega_radps=omega_radps,
    )  # fmt: skip


def test_pose_moves_on_between_frames_along_the_frame_twist() -> None:
    clock = FakeClock()
    body = WorldBody(ROBOT, ORIGIN, clock=clock)
    # World pose 1 m ahead of the origin along its heading (+y), backing at 0.3 m/s.
    body.update(_frame(1.0, 3.0, math.pi / 2, -0.3, 0.0))
    assert body.state().pose.x_m == pytest.approx(1.0)
    clock.now_s += 0.07
    pose = body.state().pose
    assert pose.x_m == pytest.approx(1.0 - 0.3 * 0.07)
    assert pose.y_m == pytest.approx(0.0, abs=1e-12)
    assert pose.theta_rad == pytest.approx(0.0, abs=1e-12)


def test_turning_body_turns_on_between_frames() -> None:
    clock = FakeClock()
    body = WorldBody(ROBOT, ORIGIN, clock=clock)
    body.update(_frame(1.0, 2.0, math.pi / 2, 0.0, math.radians(40.0)))
    clock.now_s += 0.1
    pose = body.state().pose
    assert math.degrees(pose.theta_rad) == pytest.approx(4.0)
    assert (pose.x_m, pose.y_m) == pytest.approx((0.0, 0.0), abs=1e-12)


def test_a_world_that_stopped_sending_moves_the_body_a_bounded_amount() -> None:
    clock = FakeClock()
    body = WorldBody(ROBOT, ORIGIN, clock=clock)
    body.update(_frame(1.0, 2.0, math.pi / 2, 0.3, 0.0))
    clock.now_s += 30.0
    assert body.state().pose.x_m == pytest.approx(0.3 * MAX_FRAME_AGE_S)


def test_a_new_frame_replaces_the_carried_forward_pose() -> None:
    clock = FakeClock()
    body = WorldBody(ROBOT, ORIGIN, clock=clock)
    body.update(_frame(1.0, 2.0, math.pi / 2, 0.3, 0.0))
    clock.now_s += 0.1
    body.update(_frame(1.0, 2.5, math.pi / 2, 0.0, 0.0))
    assert body.state().pose.x_m == pytest.approx(0.5)
    assert body.step(0.1).pose.x_m == pytest.approx(0.5)


def test_with_the_runs_epoch_a_late_frame_is_carried_from_its_own_instant() -> None:
    """A frame of tick 20 (t = 2 s) reaching the body 80 ms after its instant (a world
    behind its schedule, a loaded machine) describes the body 80 ms ago: the SIP sent now
    reports it 80 ms further on, where the world's motion capture has it."""
    clock, epoch_s = FakeClock(), 5_000.0
    wall = [epoch_s + 2.08]
    body = WorldBody(ROBOT, ORIGIN, clock=clock, epoch_s=epoch_s, wall=lambda: wall[0])
    late = SenseFrame(
        robot_id="r1", tick=20, t_s=2.0, dt_s=0.1, x_m=1.0, y_m=3.0, theta_rad=math.pi / 2,
        v_mps=0.3, omega_radps=math.radians(40.0),
    )  # fmt: skip
    body.update(late)
    pose = body.state().pose
    assert math.degrees(pose.theta_rad) == pytest.approx(40.0 * 0.08)
    assert math.hypot(pose.x_m - 1.0, pose.y_m) == pytest.approx(0.3 * 0.08, rel=1e-3)
    unaware = WorldBody(ROBOT, ORIGIN, clock=clock)  # (no epoch: from its arrival)
    unaware.update(late)
    assert unaware.state().pose.x_m == pytest.approx(1.0)
    # a frame from the future (clocks of two machines) is taken as of now; one far too
    # old moves the body a bounded amount
    wall[0] = epoch_s + 1.9
    body.update(late)
    assert body.state().pose.x_m == pytest.approx(1.0)
    wall[0] = epoch_s + 60.0
    body.update(late)
    assert body.state().pose.x_m == pytest.approx(1.0 + 0.3 * MAX_FRAME_AGE_S, rel=1e-2)
