"""Pose estimation in the agent brain (no I/O): a small extended Kalman filter that
predicts with wheel odometry and corrects with pose fixes and relative measurements of
the tracked robot, each applied at the time it was taken (buffer and replay).
"""

from phalanx.agents.estimation.estimator import Estimate, EstimatorStats, PoseEstimator

__all__ = ["Estimate", "EstimatorStats", "PoseEstimator"]
