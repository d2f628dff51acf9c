"""Formation errors as the paper reports them (section 5), from a run's ground truth.

For each follower against the robot it tracks:
- linear error `|l - l_d| / l_d` (and `|l - l_d|` in m),
- angular error `|phi - phi_d| / phi_d` (and `|phi - phi_d|` in deg),
- orientation error: the follower's heading against the heading a rigid formation
  would give it (theta_L + beta, DESIGN.md), in deg.
Split into the forward and the backward phase of the formation (the root's direction);
each phase is measured from `settle_s` after the switch (and the forward phase also from
`initial_settle_s`, so the convergence from the start offsets is not counted).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from phalanx.agents.control.common import rigid_body_target
from phalanx.formation import Formation
from phalanx.geometry import Pose2D, Twist2D, wrap_angle
from phalanx.messages import RobotState
from phalanx.simulator.batch import RunLog

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class Stat:
    """Max, mean and RMS of an error series."""

    max: float
    mean: float
    rms: float

    @classmethod
    def of(cls, values: FloatArray) -> Stat:
        """Statistics of `values` (NaN-filled when empty)."""
        if values.size == 0:
            return cls(math.nan, math.nan, math.nan)
        return cls(
            float(np.max(values)), float(np.mean(values)), float(np.sqrt(np.mean(values**2)))
        )


@dataclass(frozen=True)
class PhaseErrors:
    """One phase's errors, in % (as the paper) and in absolute units."""

    samples: int
    duration_s: float
    linear_pct: Stat
    angular_pct: Stat
    orientation_deg: Stat
    linear_m: Stat
    angular_deg: Stat


@dataclass(frozen=True)
class ErrorSeries:
    """Per-step error series of one follower."""

    l_m: FloatArray
    phi_rad: FloatArray
    linear_pct: FloatArray
    angular_pct: FloatArray
    orientation_deg: FloatArray
    linear_m: FloatArray
    angular_deg: FloatArray


def error_series(log: RunLog, follower: str) -> ErrorSeries:
    """Errors of `follower` against its tree leader at every step (ground truth)."""
    leader = log.formation.leader_of(follower)
    if leader is None:
        raise ValueError(f"{follower!r} is the formation root; it has no formation error")
    lt, ft = log.traces[leader], log.traces[follower]
    l_d, phi_d = log.formation.polar_of(follower, leader)
    dx, dy = ft.x_m - lt.x_m, ft.y_m - lt.y_m
    c, s = np.cos(lt.theta_rad), np.sin(lt.theta_rad)
    bx, by = c * dx + s * dy, -s * dx + c * dy
    l_m = np.hypot(bx, by)
    phi = np.mod(np.arctan2(by, bx), 2 * math.pi)
    dphi = np.abs(np.mod(phi - phi_d + math.pi, 2 * math.pi) - math.pi)
    orient = np.abs(_orientation_error_rad(log, leader, follower))
    return ErrorSeries(
        l_m=l_m,
        phi_rad=phi,
        linear_pct=100.0 * np.abs(l_m - l_d) / l_d,
        angular_pct=100.0 * dphi / phi_d,
        orientation_deg=np.degrees(orient),
        linear_m=np.abs(l_m - l_d),
        angular_deg=np.degrees(dphi),
    )


@dataclass(frozen=True)
class LiveErrors:
    """One follower's errors at one step, against the leader state it used."""

    slot_target: Pose2D
    linear_pct: float
    angular_pct: float
    orientation_deg: float


def live_errors(
    formation: Formation, follower: str, pose: Pose2D, leader: RobotState
) -> LiveErrors:
    """The paper's errors of `follower` at `pose` against `leader`'s published state
    (what a robot can know on its own, for live telemetry; `error_series` uses truth).
    """
    l_d, phi_d = formation.polar_of(follower, leader.robot_id)
    local = leader.pose.to_body(pose.position)
    l_m = local.norm()
    phi = math.atan2(local.y_m, local.x_m) % (2 * math.pi)
    dphi = abs((phi - phi_d + math.pi) % (2 * math.pi) - math.pi)
    slot = formation.slot_of(follower, leader.robot_id)
    target, _ = rigid_body_target(leader.pose, leader.twist, slot)
    return LiveErrors(
        slot_target=target,
        linear_pct=100.0 * abs(l_m - l_d) / l_d,
        angular_pct=100.0 * dphi / phi_d,
        orientation_deg=math.degrees(abs(wrap_angle(pose.theta_rad - target.theta_rad))),
    )


def _orientation_error_rad(log: RunLog, leader: str, follower: str) -> FloatArray:
    lt, ft = log.traces[leader], log.traces[follower]
    slot = log.formation.slot_of(follower, leader)
    out = np.empty(len(log.t_s))
    for k in range(len(out)):
        twist = Twist2D(float(lt.cmd_v_mps[k]), float(lt.cmd_omega_radps[k]))
        target, _ = rigid_body_target(lt.pose(k), twist, slot)
        out[k] = wrap_angle(float(ft.theta_rad[k]) - target.theta_rad)
    return out


def phase_masks(log: RunLog) -> tuple[BoolArray, BoolArray]:
    """(forward, backward) masks of settled steps.

    The phase is the formation's direction of travel, i.e. the root's (the leader
    switches first; its followers switch as its velocity changes sign, inside the
    settling time).
    """
    direction = log.traces[log.formation.root].direction
    t = log.t_s
    switch_t = np.zeros_like(t)
    last = 0.0
    for k in range(1, len(t)):
        if direction[k] != direction[k - 1]:
            last = float(t[k])
        switch_t[k] = last
    settled = t - switch_t >= log.scenario.settle_s
    forward = settled & (direction > 0) & (t >= log.scenario.initial_settle_s)
    backward = settled & (direction < 0)
    return forward, backward


def _phase(series: ErrorSeries, mask: BoolArray, dt_s: float) -> PhaseErrors:
    return PhaseErrors(
        samples=int(mask.sum()),
        duration_s=float(mask.sum()) * dt_s,
        linear_pct=Stat.of(series.linear_pct[mask]),
        angular_pct=Stat.of(series.angular_pct[mask]),
        orientation_deg=Stat.of(series.orientation_deg[mask]),
        linear_m=Stat.of(series.linear_m[mask]),
        angular_deg=Stat.of(series.angular_deg[mask]),
    )


def follower_metrics(log: RunLog, follower: str) -> dict[str, Any]:
    """Errors per phase plus limiter counters for one follower."""
    leader = log.formation.leader_of(follower)
    assert leader is not None  # noqa: S101 - error_series raised otherwise
    series = error_series(log, follower)
    forward, backward = phase_masks(log)
    l_d, phi_d = log.formation.polar_of(follower, leader)
    return {
        "leader": leader,
        "l_d_m": l_d,
        "phi_d_deg": math.degrees(phi_d),
        "forward": asdict(_phase(series, forward, log.scenario.dt_s)),
        "backward": asdict(_phase(series, backward, log.scenario.dt_s)),
        "saturations": log.saturations[follower],
        "accel_limited": log.accel_limited[follower],
    }


def run_metrics(log: RunLog) -> dict[str, Any]:
    """The whole `metrics.json` of a run."""
    followers = [r for r in log.formation.robot_ids if log.formation.leader_of(r) is not None]
    root = log.formation.root
    return {
        "scenario": log.scenario.name,
        "controller": log.scenario.controller.kind,
        "robots": len(log.traces),
        "duration_s": log.scenario.duration_s,
        "control_rate_hz": log.scenario.control_rate_hz,
        "comm_delay_s": log.scenario.comm_delay_s,
        "wall_time_s": log.wall_time_s,
        "realtime_factor": log.scenario.duration_s / max(log.wall_time_s, 1e-9),
        "runtime": log.runtime,
        "followers": {f: follower_metrics(log, f) for f in followers},
        "leader": {
            "id": root,
            "saturations": log.saturations[root],
            "accel_limited": log.accel_limited[root],
        },
        "collisions": [asdict(c) for c in log.collisions],
        "transitions": {
            rid: [asdict(e) for e in events] for rid, events in log.transitions.items()
        },
        "deadlock_reverses": sum(
            1 for e in log.transitions[root] if e.target == "DEADLOCK_REVERSE"
        ),
    }
