"""Everything a run produced, step by step: ground truth and commands of every robot,
its behaviour states, transitions and collisions. The in-process batch runner and the
world process both write one; metrics, figures and recordings read it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from phalanx.core.config import Scenario
from phalanx.core.formation import Formation
from phalanx.core.geometry import Pose2D
from phalanx.core.robot_params import RobotParams
from phalanx.core.states import TransitionEvent

FloatArray = npt.NDArray[np.float64]
# Where a run's recorded poses come from (`RunLog.pose_sources`): phalanx's own world; a
# simulator's true pose (`truth_source`); motion capture; the robot's own estimate, whose
# errors (odometry drift) the formation errors measured on it cannot show.
SIMULATED_POSE = "phalanx's simulated world (exact)"
MOCAP_POSE = "motion capture (phalanx mocap)"
ESTIMATE_POSE = "the robot's own estimate (odometry or its pose estimator)"
ESTIMATE_CAVEAT = (
    "errors of robots recorded from their own estimate are measured against what they "
    "believed: odometry drift and estimation errors are not in them"
)


def truth_source(simulator: str) -> str:
    """The pose source of a simulator's true poses (`simulator`: its name)."""
    return f"simulator's true pose ({simulator})"


@dataclass(frozen=True, slots=True)
class Collision:
    """A contact that began at `t_s` between a robot and a robot or `obstacle:<i>`."""

    t_s: float
    robot_id: str
    other: str


@dataclass
class RobotTrace:
    """One robot's run, one row per control step: ground truth and what it commanded."""

    x_m: FloatArray
    y_m: FloatArray
    theta_rad: FloatArray
    v_mps: FloatArray
    omega_radps: FloatArray
    cmd_v_mps: FloatArray
    cmd_omega_radps: FloatArray
    direction: npt.NDArray[np.int8]
    states: list[str] = field(default_factory=list)
    tracked: list[str] = field(default_factory=list)  # whom it tracked ("" while leading)
    leaders: list[str] = field(default_factory=list)  # who led the formation, in its view
    epochs: list[int] = field(default_factory=list)
    formed: list[bool] = field(default_factory=list)  # in its slot (not off avoiding)
    # What the robot published as its pose (x, y, theta: its estimate, or its odometry
    # without the estimator) and the covariance with it (xx, xy, xt, yy, yt, tt; NaN
    # where it published none), one row per step.
    estimate: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    cov: FloatArray = field(default_factory=lambda: np.zeros((0, 6)))
    # The shape it was in (`phalanx.core.shapes.ShapeKey`: from, to, morph), per step.
    shapes: list[tuple[int, int, float]] = field(default_factory=list)
    # Whether the robot's map showed the scenario's shape fitting its way (a navigating
    # leader's `PeerState.shape_fits`), per step.
    fits: list[bool] = field(default_factory=list)

    @classmethod
    def empty(cls, n: int) -> RobotTrace:
        """Zeroed arrays for `n` steps (estimates and covariances NaN)."""
        z = np.zeros
        trace = cls(z(n), z(n), z(n), z(n), z(n), z(n), z(n), np.ones(n, dtype=np.int8))
        trace.estimate, trace.cov = np.full((n, 3), np.nan), np.full((n, 6), np.nan)
        return trace

    def truncated(self, n: int) -> RobotTrace:
        """The first `n` steps."""
        return RobotTrace(
            self.x_m[:n],
            self.y_m[:n],
            self.theta_rad[:n],
            self.v_mps[:n],
            self.omega_radps[:n],
            self.cmd_v_mps[:n],
            self.cmd_omega_radps[:n],
            self.direction[:n],
            self.states[:n],
            self.tracked[:n],
            self.leaders[:n],
            self.epochs[:n],
            self.formed[:n],
            self.estimate[:n],
            self.cov[:n],
            self.shapes[:n],
            self.fits[:n],
        )

    def pose(self, k: int) -> Pose2D:
        """Ground-truth pose at step `k`."""
        return Pose2D(float(self.x_m[k]), float(self.y_m[k]), float(self.theta_rad[k]))


@dataclass
class RunLog:
    """Everything a run produced, for metrics, figures and telemetry."""

    scenario: Scenario
    robot: RobotParams
    formation: Formation
    t_s: FloatArray
    traces: dict[str, RobotTrace]
    transitions: dict[str, list[TransitionEvent]]
    collisions: list[Collision]
    saturations: dict[str, int]
    accel_limited: dict[str, int]
    wall_time_s: float = 0.0
    runtime: dict[str, Any] = field(default_factory=dict)
    # Where each robot's recorded poses come from (absent: SIMULATED_POSE).
    pose_sources: dict[str, str] = field(default_factory=dict)

    def pose_source(self, robot_id: str) -> str:
        """Where robot `robot_id`'s recorded poses come from."""
        return self.pose_sources.get(robot_id, SIMULATED_POSE)
