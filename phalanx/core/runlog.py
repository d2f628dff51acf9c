"""Everything a run produced, step by step: ground truth and commands of every robot,
its behaviour states, transitions and collisions. The in-process batch runner and the
world process both write one; metrics, figures and recordings read it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from phalanx.core.config import RobotParams, Scenario
from phalanx.core.formation import Formation
from phalanx.core.geometry import Pose2D
from phalanx.core.states import TransitionEvent

FloatArray = npt.NDArray[np.float64]


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
