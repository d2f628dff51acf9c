"""Formation errors as the paper reports them (section 5), from a run's ground truth.

For each follower against the robot it tracks:
- linear error `|l - l_d| / l_d` (and `|l - l_d|` in m),
- angular error `|phi - phi_d| / phi_d` (and `|phi - phi_d|` in deg),
- orientation error: the follower's heading against the heading a rigid formation
  would give it (theta_L + beta, `phalanx.core.rigid_body`), in deg.
Split into the forward and the backward phase of the formation (its leader's direction);
each phase is measured from `settle_s` after the switch (and the forward phase also from
`initial_settle_s`, so the convergence from the start offsets is not counted).

Leadership can pass, and a robot tracks whichever neighbour the re-rooted follow tree
gives it (`RobotTrace.tracked`): errors are taken against the robot tracked at each step,
and a robot is measured only while it follows. Navigation runs add `navigation_metrics`:
goal, time to goal, collisions by kind, deadlock reverses, leadership changes, why a
group got stuck, and the formation error outside obstacle-avoidance episodes.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from phalanx.core.geometry import Twist2D, wrap_angle
from phalanx.core.rigid_body import rigid_body_target
from phalanx.core.runlog import ESTIMATE_CAVEAT, ESTIMATE_POSE, RobotTrace, RunLog
from phalanx.core.shapes import SCENARIO_SHAPE, ShapeBook, ShapeKey
from phalanx.core.states import ROBOT_STATES

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

# The backward-phase bounds phalanx holds its formation to with perfect sensing (the
# paper reports +-2 %, +-0.8 % and +-1.3 for its own): the worst of each error series.
# A step of the leader's commanded twist in one control step at least this large starts
# a transient of the rigid-formation target (`steady_forward_mask`): its script's segment
# changes, not its steering's corrections.
TWIST_STEP_RADPS = math.radians(1.0)
TWIST_STEP_MPS = 0.05
CORE_BOUNDS: dict[str, float] = {"linear_pct": 0.5, "angular_pct": 0.3, "orientation_deg": 0.5}


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
    """Errors of `follower` against the robot it tracked at every step (ground truth);
    NaN while it led the formation.
    """
    parents = tracked_series(log, follower)
    distinct = set(parents)
    if "" not in distinct and len(distinct) == 1:
        return _series_against(log, follower, parents[0], np.ones(len(log.t_s), dtype=bool))
    if distinct == {""}:
        raise ValueError(f"{follower!r} led the formation throughout; it has no formation error")
    n = len(log.t_s)
    parts = {
        name: np.full(n, np.nan)
        for name in ("l_m", "phi_rad", "linear_pct", "angular_pct", "orientation_deg")
    }
    parts |= {"linear_m": np.full(n, np.nan), "angular_deg": np.full(n, np.nan)}
    for parent in sorted(distinct - {""}):
        mask = np.array([p == parent for p in parents])
        part = _series_against(log, follower, parent, mask)
        for name, values in parts.items():
            values[mask] = getattr(part, name)[mask]
    return ErrorSeries(**parts)


def tracked_series(log: RunLog, robot: str) -> list[str]:
    """Whom `robot` tracked at each step ("" while leading): recorded, else configured."""
    tracked = log.traces[robot].tracked
    if len(tracked) == len(log.t_s):
        return list(tracked)
    return [log.formation.leader_of(robot) or ""] * len(log.t_s)


def leader_series(log: RunLog) -> list[str]:
    """The robot leading the formation at each step (the first that tracked nobody)."""
    ids = log.formation.robot_ids
    tracked = {rid: tracked_series(log, rid) for rid in ids}
    root = log.formation.root
    return [next((r for r in ids if tracked[r][k] == ""), root) for k in range(len(log.t_s))]


def is_follower(log: RunLog, robot: str) -> bool:
    """Whether `robot` followed at some step."""
    return any(tracked_series(log, robot))


def _series_against(log: RunLog, follower: str, leader: str, mask: BoolArray) -> ErrorSeries:
    lt, ft = log.traces[leader], log.traces[follower]
    l_d, phi_d = _desired_polar(log, follower, leader)
    dx, dy = ft.x_m - lt.x_m, ft.y_m - lt.y_m
    c, s = np.cos(lt.theta_rad), np.sin(lt.theta_rad)
    bx, by = c * dx + s * dy, -s * dx + c * dy
    l_m = np.hypot(bx, by)
    phi = np.mod(np.arctan2(by, bx), 2 * math.pi)
    dphi = np.abs(np.mod(phi - phi_d + math.pi, 2 * math.pi) - math.pi)
    orient = np.abs(_orientation_error_rad(log, leader, follower, mask))
    return ErrorSeries(
        l_m=l_m,
        phi_rad=phi,
        linear_pct=100.0 * np.abs(l_m - l_d) / l_d,
        angular_pct=_percent_of(dphi, phi_d),
        orientation_deg=np.degrees(orient),
        linear_m=np.abs(l_m - l_d),
        angular_deg=np.degrees(dphi),
    )


def _percent_of(error: FloatArray, desired: FloatArray | float) -> FloatArray:
    """`error` in percent of `desired`; NaN where nothing is desired (a slot dead ahead,
    bearing 0, between two shapes).
    """
    desired_arr = np.broadcast_to(np.asarray(desired, dtype=np.float64), error.shape)
    out = np.full(error.shape, np.nan)
    np.divide(100.0 * error, desired_arr, out=out, where=desired_arr != 0.0)
    return out


def _orientation_error_rad(log: RunLog, leader: str, follower: str, mask: BoolArray) -> FloatArray:
    lt, ft = log.traces[leader], log.traces[follower]
    slot = log.formation.slot_of(follower, leader)
    keys = _shape_keys(log, follower)
    book = ShapeBook(log.formation) if keys else None
    out = np.full(len(log.t_s), np.nan)
    for k in np.flatnonzero(mask).tolist():
        twist = Twist2D(float(lt.cmd_v_mps[k]), float(lt.cmd_omega_radps[k]))
        if book is not None:
            slot = book.formation(keys[k]).slot_of(follower, leader)
        target, _ = rigid_body_target(lt.pose(k), twist, slot)
        out[k] = wrap_angle(float(ft.theta_rad[k]) - target.theta_rad)
    return out


def _shape_keys(log: RunLog, robot: str) -> list[ShapeKey]:
    """The shape `robot` was in at every step, or [] if always the scenario's."""
    shapes = log.traces[robot].shapes
    if len(shapes) != len(log.t_s) or all(s == (0, 0, 1.0) for s in shapes):
        return []
    return [ShapeKey(*s) for s in shapes]


def _desired_polar(
    log: RunLog, follower: str, leader: str
) -> tuple[float | FloatArray, float | FloatArray]:
    """(l_d, phi_d) of `follower` against `leader`: the scenario's shape's, or per step
    the shape the follower was in (a group that changed its shape on the way).
    """
    keys = _shape_keys(log, follower)
    if not keys:
        return log.formation.polar_of(follower, leader)
    book = ShapeBook(log.formation)
    polar = {k: book.formation(k).polar_of(follower, leader) for k in set(keys)}
    return (
        np.array([polar[k][0] for k in keys]),
        np.array([polar[k][1] for k in keys]),
    )


def phase_masks(log: RunLog) -> tuple[BoolArray, BoolArray]:
    """(forward, backward) masks of settled steps.

    The phase is the formation's direction of travel, i.e. its leader's (the leader
    switches first; its followers switch as its velocity changes sign, inside the
    settling time).
    """
    direction = leader_direction(log)
    switched = np.concatenate(([False], direction[1:] != direction[:-1]))
    settled = _settled(log, switched)
    forward = settled & (direction > 0) & (log.t_s >= log.scenario.initial_settle_s)
    backward = settled & (direction < 0)
    return forward, backward


def _settled(log: RunLog, switched: BoolArray) -> BoolArray:
    """The steps `settle_s` or more after the last switch (none before the first)."""
    t = log.t_s
    switch_t = np.maximum.accumulate(np.where(switched, t, 0.0))
    return np.asarray(t - switch_t >= log.scenario.settle_s, dtype=bool)


def steady_forward_mask(log: RunLog, forward: BoolArray) -> BoolArray:
    """`forward`, less `settle_s` after each step of a scripted leader's twist.

    The paper's leader drives piecewise constant twists: when its yaw rate steps, the
    heading a rigid formation gives a follower jumps with it (by beta = atan2(w s_x,
    v - w s_y): 18 deg for the wedge's slots when it steps from 0 to 3 deg/s), which no
    robot on wheels follows at once. The forward phase counts those transients; this
    one measures the formation once each has passed.
    """
    lead = log.traces[log.formation.root]
    v, w = lead.cmd_v_mps, lead.cmd_omega_radps
    stepped = (np.abs(np.diff(w, prepend=w[:1])) > TWIST_STEP_RADPS) | (
        np.abs(np.diff(v, prepend=v[:1])) > TWIST_STEP_MPS
    )
    return forward & _settled(log, stepped)


def leader_direction(log: RunLog) -> npt.NDArray[np.int8]:
    """The direction of whichever robot led the formation, at each step."""
    leaders = leader_series(log)
    if len(set(leaders)) == 1:
        return log.traces[leaders[0]].direction
    return np.array([log.traces[r].direction[k] for k, r in enumerate(leaders)], dtype=np.int8)


def _phase(series: ErrorSeries, mask: BoolArray, dt_s: float) -> PhaseErrors:
    mask = mask & np.isfinite(series.linear_pct)  # steps it led: nothing to measure
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
    parents = [p for p in tracked_series(log, follower) if p]
    leader = max(set(parents), key=parents.count)  # the robot it tracked most
    series = error_series(log, follower)
    forward, backward = phase_masks(log)
    l_d, phi_d = log.formation.polar_of(follower, leader)
    dt_s = log.scenario.dt_s
    out = {
        "leader": leader,
        "l_d_m": l_d,
        "phi_d_deg": math.degrees(phi_d),
        "forward": asdict(_phase(series, forward, dt_s)),
        "backward": asdict(_phase(series, backward, dt_s)),
        "saturations": log.saturations[follower],
        "accel_limited": log.accel_limited[follower],
    }
    if log.scenario.leader_profile is not None:
        out["forward_steady"] = asdict(_phase(series, steady_forward_mask(log, forward), dt_s))
    return out


# States in which a robot is off its slot on purpose, or the shape is being turned about:
# a formation's error is not measured then, nor for `settle_s` after.
EPISODE_STATES = frozenset(
    {"AVOID", "EMERGENCY_STOP", "HOLD", "JOIN", "DEADLOCK_TURN", "STUCK"} | ROBOT_STATES
)
TURNING_ON_THE_SPOT_MPS = 0.005


def episode_mask(log: RunLog, *, reshaping: bool = True) -> BoolArray:
    """Steps inside an obstacle-avoidance (or stop, or turn-away) episode of any robot:
    from leaving its slot until it is back in it (`formed`), or the leader turning the
    shape on the spot to get round something; with `reshaping`, also while the group
    slides from one shape to another (a planned change, not an avoidance: its own share
    in `navigation_metrics`); each episode extended by `settle_s`; and the first
    `initial_settle_s`.
    """
    t = log.t_s
    busy = np.zeros(len(t), dtype=bool)
    for tr in log.traces.values():
        busy |= np.array([s in EPISODE_STATES for s in tr.states], dtype=bool)
        if len(tr.formed) == len(t):
            busy |= ~np.array(tr.formed, dtype=bool)
        if reshaping:
            busy |= reshaping_mask(log, tr)
    for k, rid in enumerate(leader_series(log)):
        tr = log.traces[rid]
        spinning = (
            abs(tr.cmd_v_mps[k]) < TURNING_ON_THE_SPOT_MPS and abs(tr.cmd_omega_radps[k]) > 0.01
        )
        busy[k] |= bool(spinning) and tr.states[k] in ("NAVIGATE", "WANDER")
    settle_steps = round(log.scenario.settle_s / log.scenario.dt_s)
    out = busy.copy()
    ends = np.flatnonzero(busy[:-1] & ~busy[1:]) + 1
    for end in ends:
        out[end : end + settle_steps] = True
    return out | (t < log.scenario.initial_settle_s)


def reshaping_mask(log: RunLog, trace: RobotTrace) -> BoolArray:
    """Steps a robot was between two shapes (or in the leader's RESHAPE)."""
    n = len(log.t_s)
    sliding = np.zeros(n, dtype=bool)
    if len(trace.shapes) == n:
        sliding |= np.array([s[2] < 1.0 for s in trace.shapes], dtype=bool)
    reshaping: BoolArray = np.array([s == "RESHAPE" for s in trace.states], dtype=bool)
    return sliding | reshaping


def navigation_metrics(log: RunLog) -> dict[str, Any]:
    """Goal, time to goal, collisions by kind, deadlocks, leadership, stuck, and the
    formation error outside avoidance episodes (worst follower, all followers' steps).
    """
    transitions = [e for events in log.transitions.values() for e in events]
    arrived = sorted(e.t_s for e in transitions if e.target == "ARRIVED")
    stuck = sorted((e.t_s, e.reason) for e in transitions if e.target == "STUCK")
    robots = set(log.traces)
    obstacle_hits = [c for c in log.collisions if c.other not in robots]
    robot_hits = {tuple(sorted((c.robot_id, c.other))) for c in log.collisions if c.other in robots}
    calm = ~episode_mask(log)
    followers = [r for r in log.formation.robot_ids if is_follower(log, r)]
    errors = _calm_errors(log, followers, calm)
    busy_share = float(episode_mask(log, reshaping=False).mean()) if calm.size else math.nan
    sliding = np.zeros(len(log.t_s), dtype=bool)
    for tr in log.traces.values():
        sliding |= reshaping_mask(log, tr)
    epochs = [max(tr.epochs, default=0) for tr in log.traces.values()]
    return {
        "goal_reached": bool(arrived),
        "time_to_goal_s": arrived[0] if arrived else None,
        "collisions_obstacle": len(obstacle_hits),
        "collisions_robot": len(robot_hits),
        "deadlock_reverses": sum(1 for e in transitions if e.target == "DEADLOCK_REVERSE"),
        "leadership_changes": max(epochs, default=0),
        "stuck": bool(stuck),
        "stuck_reason": stuck[0][1] if stuck else "",
        "episode_share": busy_share,
        "reshaping_share": float(sliding.mean()) if sliding.size else math.nan,
        "calm": errors,
        "reshapes": sum(1 for e in transitions if e.target == "RESHAPE"),
        **_scenario_shape_shares(log),
    }


def _scenario_shape_shares(log: RunLog) -> dict[str, float]:
    """The share of steps the group (its leader's view) was in the scenario's shape
    (`scenario_shape_share`), the share its leader's map showed that shape fitting the
    way (`fits_share`: `ShapeKeeper.scenario_fits`), and the share of those it was in it
    (`scenario_shape_when_fits`; 1 when it never fitted).
    """
    series = scenario_shape_series(log)
    if series is None:
        return {"scenario_shape_share": 1.0, "fits_share": 1.0, "scenario_shape_when_fits": 1.0}
    in_shape, fits = series
    n, fitting = len(fits), int(np.count_nonzero(fits))
    kept = int(np.count_nonzero(in_shape & fits))
    return {
        "scenario_shape_share": int(np.count_nonzero(in_shape)) / n,
        "fits_share": fitting / n,
        "scenario_shape_when_fits": kept / fitting if fitting else 1.0,
    }


def scenario_shape_series(log: RunLog) -> tuple[BoolArray, BoolArray] | None:
    """Per step, as the robot leading then saw it: whether the group was settled in the
    scenario's shape (whichever shape it came back from), and whether the leader's map
    showed that shape fitting the way; None for a run without a step, or whose traces
    do not record both.
    """
    leaders = leader_series(log)
    n = len(leaders)
    if not n or any(len(tr.shapes) != n or len(tr.fits) != n for tr in log.traces.values()):
        return None
    in_shape = [key.settled_in(SCENARIO_SHAPE) for key in leader_shape_keys(log, leaders)]
    fits = [log.traces[rid].fits[k] for k, rid in enumerate(leaders)]
    return np.array(in_shape, dtype=bool), np.array(fits, dtype=bool)


def leader_shape_keys(log: RunLog, leaders: list[str] | None = None) -> list[ShapeKey]:
    """Per step, the shape in effect as the robot leading then saw it (`leaders`, as
    `leader_series` gives them, if already worked out).
    """
    leaders = leader_series(log) if leaders is None else leaders
    return [ShapeKey(*log.traces[rid].shapes[k]) for k, rid in enumerate(leaders)]


def _calm_errors(log: RunLog, followers: list[str], calm: BoolArray) -> dict[str, Any]:
    """Mean and max of the paper's errors over every follower's calm steps."""
    keys = ("linear_pct", "angular_pct", "orientation_deg", "linear_m", "angular_deg")
    pooled: dict[str, list[FloatArray]] = {k: [] for k in keys}
    for rid in followers:
        series = error_series(log, rid)
        mask = calm & np.isfinite(series.linear_pct)
        for k in keys:
            pooled[k].append(getattr(series, k)[mask])
    out: dict[str, Any] = {"samples": int(sum(a.size for a in pooled["linear_pct"]))}
    for k in keys:
        values = np.concatenate(pooled[k]) if pooled[k] else np.zeros(0)
        out[k] = {
            "mean": float(values.mean()) if values.size else math.nan,
            "max": float(values.max()) if values.size else math.nan,
        }
    return out


def run_metrics(log: RunLog) -> dict[str, Any]:
    """The whole `metrics.json` of a run."""
    followers = [r for r in log.formation.robot_ids if is_follower(log, r)]
    root = log.formation.root
    sources = {rid: log.pose_source(rid) for rid in log.traces}
    metrics: dict[str, Any] = {
        "scenario": log.scenario.name,
        "controller": log.scenario.controller.kind,
        "robots": len(log.traces),
        "duration_s": log.scenario.duration_s,
        "control_rate_hz": log.scenario.control_rate_hz,
        "comm_delay_s": log.scenario.comm_delay_s,
        "wall_time_s": log.wall_time_s,
        "realtime_factor": log.scenario.duration_s / max(log.wall_time_s, 1e-9),
        "runtime": log.runtime,
        "pose_source": sources,
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
            1
            for events in log.transitions.values()
            for e in events
            if e.target == "DEADLOCK_REVERSE"
        ),
    }
    if ESTIMATE_POSE in sources.values():
        metrics["pose_caveat"] = ESTIMATE_CAVEAT
    if log.scenario.leader_profile is None:
        metrics["navigation"] = navigation_metrics(log)
    if log.scenario.localisation.estimator:
        from phalanx.analysis.estimation import estimation_metrics

        metrics["estimation"] = estimation_metrics(log)
    return metrics
