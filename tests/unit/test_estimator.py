"""The pose estimator: honest covariance, late measurements at their own time, relative
measurements that tie a follower to the frame of the robot it sees."""

from __future__ import annotations

import itertools
import math
import random

import numpy as np
import pytest

from phalanx.agents.estimation.ekf import Belief, predict, update_pose
from phalanx.agents.estimation.estimator import PoseEstimator, process_noise
from phalanx.core.fixes import PoseFix, RelativeFix
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.localisation import LocalisationConfig, MocapSource, OdometryErrors
from phalanx.core.peers import PeerState
from phalanx.core.robot import Odometry
from phalanx.simulator.sensors.odometry import WheelOdometry

TRACK_M = 0.38
ERRORS = OdometryErrors(scale_std_frac=0.0005, walk_std_m=0.001)
CONFIG = LocalisationConfig(estimator=True, odometry=ERRORS, initial_std_m=0.0, initial_std_deg=0.0)


def _odometry(t_s: float, pose: Pose2D) -> Odometry:
    return Odometry(pose, Twist2D(0.15, 0.0), t_s)


def _arc_poses(steps: int, *, v: float = 0.15, w: float = 0.05, dt: float = 0.1) -> list[Pose2D]:
    poses, x, y, th = [], 0.0, 0.0, 0.0
    for _ in range(steps + 1):
        poses.append(Pose2D(x, y, th))
        x += v * dt * math.cos(th + 0.5 * w * dt)
        y += v * dt * math.sin(th + 0.5 * w * dt)
        th += w * dt
    return poses


def test_odometry_covariance_matches_the_odometry_error_it_models() -> None:
    """Odometry alone: the filter's covariance after 30 m against the spread of 2000
    simulated robots' odometry errors (scale errors drawn per robot, random walk)."""
    steps, robots = 2000, 2000
    truth = _arc_poses(steps, w=0.02)
    sim = WheelOdometry(ERRORS, track_m=TRACK_M, seed=3)
    for _ in range(robots):
        sim.add_robot(0.0, 0.0, 0.0)
    estimator = PoseEstimator(CONFIG, track_m=TRACK_M, robot_id="r1")
    for k, (a, b) in enumerate(itertools.pairwise(truth)):
        local = a.relative(b)
        ds = math.hypot(local.x_m, local.y_m)
        sim.step(np.full(robots, ds), np.full(robots, local.theta_rad))
        estimate = estimator.step(_odometry(0.1 * (k + 1), b))
    end = truth[-1]
    errors = sim.pose - (end.x_m, end.y_m, end.theta_rad)
    errors[:, 2] = np.mod(errors[:, 2] + math.pi, 2 * math.pi) - math.pi
    empirical = np.cov(errors.T)
    xx, xy, xt, yy, yt, tt = estimate.cov
    model = np.array([[xx, xy, xt], [xy, yy, yt], [xt, yt, tt]])
    # variances within 20 % (2000 draws: about 6 % sampling error), heading included
    assert np.diag(empirical) == pytest.approx(np.diag(model), rel=0.2)
    # and the error's shape: the average NEES over the robots is 3
    nees = np.einsum("ij,ij->i", errors, np.linalg.solve(model, errors.T).T)
    assert nees.mean() == pytest.approx(3.0, rel=0.15)


def test_a_late_fix_is_applied_at_the_time_it_was_taken() -> None:
    truth = _arc_poses(10)
    fix = PoseFix(0.35, truth[3].x_m + 0.03, truth[3].y_m - 0.02, truth[3].theta_rad, 0.002, 0.01)
    config = LocalisationConfig(estimator=True, odometry=ERRORS, initial_std_m=0.05)
    on_time = PoseEstimator(config, track_m=TRACK_M, robot_id="r1")
    late = PoseEstimator(config, track_m=TRACK_M, robot_id="r1")
    as_new = PoseEstimator(config, track_m=TRACK_M, robot_id="r1")
    stale = PoseFix(
        0.75, *(getattr(fix, f) for f in ("x_m", "y_m", "theta_rad", "std_m", "std_rad"))
    )
    for k, pose in enumerate(truth):
        t = 0.1 * k
        a = on_time.step(_odometry(t, pose), fixes=(fix,) if k == 4 else ())
        b = late.step(_odometry(t, pose), fixes=(fix,) if k == 7 else ())
        c = as_new.step(_odometry(t, pose), fixes=(stale,) if k == 7 else ())
    assert (b.pose.x_m, b.pose.y_m, b.pose.theta_rad) == pytest.approx(
        (a.pose.x_m, a.pose.y_m, a.pose.theta_rad), abs=1e-12
    )
    assert b.cov == pytest.approx(a.cov, abs=1e-15)
    assert late.stats.counts["replayed"] == 1
    assert on_time.stats.counts["fix_fused"] == late.stats.counts["fix_fused"] == 1
    # the same numbers taken as new would put the robot elsewhere
    assert math.hypot(c.pose.x_m - a.pose.x_m, c.pose.y_m - a.pose.y_m) > 1e-3


def test_a_fix_older_than_the_history_is_dropped_and_counted() -> None:
    estimator = PoseEstimator(CONFIG, track_m=TRACK_M, robot_id="r1")
    poses = _arc_poses(30)
    for k, pose in enumerate(poses):
        old = (PoseFix(0.05, 5.0, 5.0, 0.0, 0.002, 0.01),) if k == 25 else ()
        estimate = estimator.step(_odometry(0.1 * k, pose), fixes=old)
    assert estimator.stats.counts["late_dropped"] == 1
    assert estimate.pose.x_m == pytest.approx(poses[-1].x_m)


def _turning_with_late_odometry(stamp_std_s: float) -> PoseEstimator:
    """Ten seconds of a robot turning at 40 deg/s with motion-capture fixes at 50 Hz and
    odometry stamped 0-40 ms after its reading was taken (a driver stamps a reading when
    it arrives, later on a loaded computer)."""
    mocap = MocapSource(stamp_std_s=stamp_std_s)
    config = LocalisationConfig(estimator=True, odometry=ERRORS, mocap=mocap)
    estimator = PoseEstimator(config, track_m=TRACK_M, robot_id="r1")
    w, late = math.radians(40.0), random.Random(5)
    truth = _arc_poses(1000, v=0.1, w=w, dt=0.01)  # (every 10 ms)
    for k in range(0, 1000, 10):
        taken = max(0, k - late.randrange(5))
        odometry = Odometry(truth[taken], Twist2D(0.1, w), 0.01 * k)
        fixes = tuple(
            PoseFix(0.01 * j, truth[j].x_m, truth[j].y_m, truth[j].theta_rad, 0.002, 0.00175)
            for j in range(k - 8, k + 1, 2)
            if j >= 0
        )
        estimator.step(odometry, fixes=fixes)
    return estimator


def test_a_fix_counts_as_uncertain_by_the_motion_over_its_timing_error() -> None:
    """During a fast turn odometry a few tens of milliseconds late says the heading is a
    degree or two elsewhere than the fixes: ten times their own error. Counted uncertain
    by the robot's motion over `stamp_std_s`, every fix is fused; without, the filter
    (sure of its heading after a few fixes) shuts a fifth of them out."""
    tolerant = _turning_with_late_odometry(0.02).stats.counts
    strict = _turning_with_late_odometry(0.0).stats.counts
    assert tolerant["fix_gated"] == 0 < tolerant["fix_fused"]
    assert strict["fix_gated"] > 0.15 * (strict["fix_gated"] + strict["fix_fused"])


def test_an_outlier_fails_the_gate() -> None:
    belief = Belief(0.0, 0.0, 0.0, (1e-4, 0.0, 0.0, 1e-4, 0.0, 1e-4))
    r = (4e-6, 0.0, 0.0, 4e-6, 0.0, 1e-4)
    assert update_pose(belief, (0.005, 0.0, 0.0), r, 25.0) is not None
    assert update_pose(belief, (1.0, 0.0, 0.0), r, 25.0) is None


def test_prediction_moves_along_the_arc() -> None:
    noise = process_noise(CONFIG, TRACK_M)
    b = predict(Belief(0.0, 0.0, 0.0, (0.0,) * 6), math.pi / 2, math.pi / 2, 1.0, noise)
    assert (b.x, b.y, b.th) == pytest.approx((1.0, 1.0, math.pi / 2))


def _lead(pose: Pose2D, cov: tuple[float, ...]) -> PeerState:
    return PeerState(
        robot_id="r1", seq=1, stamp_s=0.0, x_m=pose.x_m, y_m=pose.y_m,
        theta_rad=pose.theta_rad, v_mps=0.0, omega_radps=0.0, fsm_state="NAVIGATE", cov=cov,
    )  # fmt: skip


def test_relative_measurements_put_a_follower_in_its_leaders_frame() -> None:
    """The leader believes it is at (5, 2) heading 90 deg (wherever it really is); a
    follower that sees it 1 m ahead, heading the same way, is 1 m behind that estimate,
    and publishes the leader's uncertainty with its own."""
    leader_cov = (0.04, 0.0, 0.0, 0.04, 0.0, 0.01)
    lead = _lead(Pose2D(5.0, 2.0, math.pi / 2), leader_cov)
    config = LocalisationConfig(estimator=True, odometry=ERRORS, initial_std_m=0.5)
    estimator = PoseEstimator(config, track_m=TRACK_M, robot_id="r2")
    start = Pose2D(4.6, 0.9, math.pi / 2 + 0.05)  # its odometry's guess, 0.17 m off
    for k in range(40):
        t = 0.1 * k
        seen = RelativeFix(t - 0.05, "r1", 1.0, 0.0, 0.02, math.radians(1), 0.0, math.radians(1))
        estimate = estimator.step(
            Odometry(start, Twist2D(0.0, 0.0), t), relative=(seen,), anchors={"r1": lead}
        )
    assert (estimate.pose.x_m, estimate.pose.y_m) == pytest.approx((5.0, 1.0), abs=0.01)
    assert estimate.pose.theta_rad == pytest.approx(math.pi / 2, abs=math.radians(0.5))
    assert estimate.cov[0] > leader_cov[0]
    assert estimate.cov[3] > leader_cov[3]
    # a measurement of a robot it may not use is left out and counted
    estimator.step(
        Odometry(start, Twist2D(0.0, 0.0), 4.0),
        relative=(RelativeFix(3.95, "r3", 1.0, 0.0, 0.02, 0.02),),
        anchors={"r1": lead},
    )
    assert estimator.stats.counts["relative_not_anchor"] == 1


def _first_state(path: str) -> PeerState:
    from phalanx.agents.agent import Agent, Observation
    from phalanx.core.config_files import CONFIG_ROOT, load_robot, load_scenario
    from phalanx.core.formation import scenario_formation
    from phalanx.core.robot import RobotStatus

    scenario = load_scenario(CONFIG_ROOT / "scenarios" / path)
    robot = load_robot(scenario.robot)
    agent = Agent("r2", scenario=scenario, robot=robot, formation=scenario_formation(scenario))
    start = scenario.start_pose("r2")
    observation = Observation(Odometry(start, Twist2D(0.0, 0.0), 0.0), RobotStatus())
    return agent.step(observation, {}, 0.0).state


def test_perfect_sensing_publishes_no_covariance_and_the_estimator_publishes_one() -> None:
    """The paper's scenarios run no estimator (their trajectories stay bit-identical); a
    real_* scenario's agent publishes its estimate's covariance."""
    assert _first_state("paper_wedge.toml").cov == ()
    cov = _first_state("real_wedge.toml").cov
    assert len(cov) == 6
    assert cov[0] == pytest.approx(0.01**2)  # initial_std_m


def _slipping(outliers: range = range(0)) -> tuple[PoseEstimator, list[float]]:
    """Ten seconds at 0.15 m/s with motion-capture fixes at 50 Hz (stamped on the
    odometry's timeline, fused at each 10 Hz step), the odometry turned 3 deg at 2 s by a
    wheel that slipped; `outliers`: the fixes (by index, 0.02 s apart) 1 m off. Returns
    the estimator and its position error at each step."""
    config = LocalisationConfig(estimator=True, odometry=ERRORS, mocap=MocapSource())
    estimator = PoseEstimator(config, track_m=TRACK_M, robot_id="r1")
    truth = _arc_poses(500, w=0.0, dt=0.02)
    odometry, slip, errors = [truth[0]], Pose2D(0.0, 0.0, math.radians(3.0)), []
    for k in range(1, 501):
        moved = odometry[-1].compose(slip) if k == 100 else odometry[-1]
        odometry.append(moved.compose(truth[k - 1].relative(truth[k])))
    fixes = [
        PoseFix(0.02 * k, p.x_m + (1.0 if k in outliers else 0.0), p.y_m, p.theta_rad, 0.002,
                0.00175)
        for k, p in enumerate(truth)
    ]  # fmt: skip
    for k in range(5, 501, 5):
        reading = Odometry(odometry[k], Twist2D(0.15, 0.0), 0.02 * k)
        got = estimator.step(reading, fixes=tuple(fixes[k - 4 : k + 1]))
        errors.append(math.hypot(got.pose.x_m - truth[k].x_m, got.pose.y_m - truth[k].y_m))
    return estimator, errors


def test_a_filter_that_refuses_every_fix_for_half_a_second_takes_the_newest() -> None:
    """A slip turns the odometry 3 deg in one step: the filter, sure of its heading,
    refuses the fixes that disagree and would drive on odometry alone from there; after
    half a second of refusals it takes the newest fix as its belief and fuses again."""
    estimator, errors = _slipping()
    counts = estimator.stats.counts
    assert counts["fix_relocalised"] == 1, counts
    assert counts["fix_gated"] > 0
    assert max(errors[-50:]) < 0.003  # the last five seconds: on the fixes again
    assert max(errors) < 0.02  # (3 deg over the half second at 0.15 m/s: 4 mm)


def test_a_burst_of_outliers_shorter_than_half_a_second_is_refused() -> None:
    estimator, errors = _slipping(outliers=range(300, 315))  # 6.0-6.3 s
    counts = estimator.stats.counts
    assert counts["fix_relocalised"] == 1, counts  # the slip's, not the outliers'
    assert max(errors[40:]) < 0.003  # the outliers never pulled the estimate
