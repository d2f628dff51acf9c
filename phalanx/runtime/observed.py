"""Robots that move on their own, recorded rather than simulated.

Real robots, or robots another simulator moves (AMRISim): the world process places them
where they were seen, tick by tick, and writes the run's record from the best pose
source it hears of each:

1. a simulator's true pose (`robot/<id>/truth`, which the robot's agent passes on from
   its driver: AMRISim's SIMSTAT);
2. motion capture (`robot/<id>/fix` from `phalanx mocap`): an external measurement, with
   the system's own noise and latency;
3. else the robot's own estimate, as it published it in its state: odometry (or its
   pose estimator), whose drift the formation errors then do not show.

Samples are kept in fleet time (the run's epoch taken off their Unix stamps). The live
pose at a tick is the newest sample carried forward along its twist; the record is
interpolated between the samples on either side of each tick once the run is over, so a
sample that arrived late still counts.
"""

from __future__ import annotations

import bisect
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Final

import numpy as np

from phalanx.core.errors import ConfigError
from phalanx.core.geometry import Pose2D, Twist2D, dead_reckon, wrap_angle
from phalanx.core.runlog import ESTIMATE_POSE, MOCAP_POSE, FloatArray, truth_source
from phalanx.wire.bounds import FleetBounds
from phalanx.wire.keys import robots_key
from phalanx.wire.positions import PoseFixMessage, TruthMessage
from phalanx.wire.transport import FleetSession

# A pose is carried forward along its twist at most this long (s): past it, the robot is
# taken to stand where it was last seen (a source that stopped sending).
CARRY_MAX_S: Final = 0.5
# At most this many samples a second are kept of one robot (a flood is dropped, counted),
# and only those stamped within this long (s) before now or this long after (clocks in
# step: docs/DEPLOYMENT.md), so that a stamp far out cannot shut the later ones out.
MAX_RATE_HZ: Final = 200.0
MAX_AGE_S: Final = 10.0
MAX_AHEAD_S: Final = 1.0


@dataclass
class Track:
    """One robot's pose samples in fleet time, in time order: t, x, y, theta, v, omega."""

    source: str = ""
    rows: list[tuple[float, float, float, float, float, float]] = field(default_factory=list)
    dropped: int = 0  # out of order, or beyond MAX_RATE_HZ

    def add(
        self, row: tuple[float, float, float, float, float, float], capacity: int, now_s: float
    ) -> None:
        """Keep `row` if it is stamped near `now_s` (fleet time), after the last by the
        rate's interval at least, and there is room.
        """
        t = row[0]
        timely = now_s - MAX_AGE_S <= t <= now_s + MAX_AHEAD_S
        later = not self.rows or t >= self.rows[-1][0] + 1.0 / MAX_RATE_HZ
        if not (timely and later) or len(self.rows) >= capacity:
            self.dropped += 1
            return
        self.rows.append(row)

    def at(self, t_s: float) -> tuple[Pose2D, Twist2D] | None:
        """The newest sample not after `t_s` carried forward to it (None: none yet)."""
        i = bisect.bisect_right(self.rows, t_s, key=lambda r: r[0])
        if i == 0:
            return None
        t, x, y, th, v, w = self.rows[i - 1]
        twist = Twist2D(v, w)
        return dead_reckon(Pose2D(x, y, th), twist, t_s - t, CARRY_MAX_S), twist

    def resampled(
        self, t_s: FloatArray, *, along_path: bool = False
    ) -> tuple[FloatArray, ...] | None:
        """x, y, theta, v, omega at every time of `t_s`: interpolated between the samples
        on either side, held before the first and after the last (None: no sample).
        `along_path`: headings from the path's direction where it says more (`path_headings`).
        """
        if not self.rows:
            return None
        t, x, y, th, v, w = (np.asarray(c, dtype=np.float64) for c in zip(*self.rows, strict=True))
        heading = np.unwrap(th)
        if along_path:
            heading = path_headings(x, y, heading, v)
        out = [np.interp(t_s, t, c) for c in (x, y, heading, v, w)]
        out[2] = (out[2] + math.pi) % (2 * math.pi) - math.pi
        return tuple(out)


# A heading is read off the path over this much of it, centred on the sample, where the
# robot turns at most PATH_TURN_RAD along it (AMRISim's positions in millimetres, its
# headings in whole degrees: the least-squares line through 0.5 m of millimetre positions
# is within 0.05 deg of the tangent).
PATH_SPAN_M = 0.5
PATH_TURN_RAD = math.radians(10.0)
MOVING_MPS = 0.02


def path_headings(x: FloatArray, y: FloatArray, heading: FloatArray, v: FloatArray) -> FloatArray:
    """`heading` (unwrapped), replaced where the robot drives on a path it turns little
    along by the direction of the least-squares line through PATH_SPAN_M of the path
    centred on each sample (turned round where it reverses): a robot on wheels goes where
    it heads, and the line's direction is the tangent at its middle on a steady arc.
    """
    s = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))))
    lo = np.searchsorted(s, s - 0.5 * PATH_SPAN_M, side="left")
    hi = np.searchsorted(s, s + 0.5 * PATH_SPAN_M, side="right")
    sums = [np.concatenate(([0.0], np.cumsum(c))) for c in (x, y, x * x, y * y, x * y)]
    n = (hi - lo).astype(np.float64)
    sx, sy, sxx, syy, sxy = (c[hi] - c[lo] for c in sums)
    with np.errstate(invalid="ignore", divide="ignore"):
        cxx, cyy, cxy = sxx - sx * sx / n, syy - sy * sy / n, sxy - sx * sy / n
    axis = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)  # the line's direction, either way
    turn = np.array(
        [np.ptp(heading[a:b]) if b > a else np.inf for a, b in zip(lo, hi, strict=True)]
    )
    whole = (s - 0.5 * PATH_SPAN_M >= 0.0) & (s + 0.5 * PATH_SPAN_M <= s[-1])
    usable = whole & (np.abs(v) >= MOVING_MPS) & (turn <= PATH_TURN_RAD) & np.isfinite(axis)
    # the line's direction nearest the heading (a line has two; reversing heads opposite)
    along = axis + math.pi * np.round((heading - axis) / math.pi)
    return np.where(usable, along, heading)


class ObservedRobots:
    """What the world hears of the robots it records (`ids`); thread-safe (Zenoh's
    callbacks add, the world's loop reads).
    """

    def __init__(
        self, ids: tuple[str, ...], *, fleet: str, epoch_s: float, bounds: FleetBounds
    ) -> None:
        self.ids, self.fleet, self.epoch_s, self.bounds = ids, fleet, epoch_s, bounds
        self.tracks = {rid: Track() for rid in ids}
        self.truths = {rid: Track() for rid in ids}  # kept apart: the better source
        self.clock_rates: dict[str, float] = {}  # a simulator's clock, as it last said
        self._capacity = int(MAX_RATE_HZ * (bounds.t_max_s + 60.0))
        self._lock = threading.Lock()

    def attach(self, session: FleetSession) -> None:
        """Hear the robots' true poses and motion-capture fixes."""
        truth, fix = robots_key(self.fleet, "truth"), robots_key(self.fleet, "fix")
        session.subscribe(truth, TruthMessage, self._on_truth, context=self.bounds)
        session.subscribe(fix, PoseFixMessage, self._on_fix, context=self.bounds)

    def _on_truth(self, _key: str, m: TruthMessage) -> None:
        if m.robot_id not in self.truths:
            return
        row = (m.stamp_s - self.epoch_s, m.x_m, m.y_m, wrap_angle(m.theta_rad), m.v_mps,
               m.omega_radps)  # fmt: skip
        with self._lock:
            track = self.truths[m.robot_id]
            track.source = track.source or truth_source(m.source)
            track.add(row, self._capacity, self._now_s())
            self.clock_rates[m.robot_id] = m.clock_rate

    def _on_fix(self, _key: str, m: PoseFixMessage) -> None:
        # (once a robot's true pose is heard, the world simulates its motion capture from
        # it and publishes on this key itself: only a robot without one takes fixes)
        if m.robot_id not in self.tracks:
            return
        with self._lock:
            if self.truths[m.robot_id].rows:
                return
            track = self.tracks[m.robot_id]
            track.source = MOCAP_POSE
            row = (m.stamp_s - self.epoch_s, m.x_m, m.y_m, m.theta_rad, 0.0, 0.0)
            track.add(row, self._capacity, self._now_s())

    def _now_s(self) -> float:
        """Fleet time now."""
        return time.time() - self.epoch_s

    def has_truth(self, robot_id: str) -> bool:
        """Whether a simulator's true pose of the robot has been heard."""
        with self._lock:
            return bool(self.truths[robot_id].rows)

    def at(self, robot_id: str, t_s: float) -> tuple[Pose2D, Twist2D] | None:
        """Where the robot is at fleet time `t_s`, from the best source heard (None:
        nothing heard yet: the world leaves it where it is).
        """
        with self._lock:
            truth = self.truths[robot_id]
            return (truth if truth.rows else self.tracks[robot_id]).at(t_s)

    def record(self, robot_id: str, t_s: FloatArray) -> tuple[str, tuple[FloatArray, ...] | None]:
        """The pose source named for the record, and the robot's x, y, theta, v, omega at
        every tick (None: nothing heard: the record takes its own estimate).
        """
        with self._lock:
            truth = self.truths[robot_id].resampled(t_s, along_path=True)
            if truth is not None:
                return self.truths[robot_id].source, truth
            rows = self.tracks[robot_id].resampled(t_s)
            if rows is not None:
                return self.tracks[robot_id].source, rows
        return ESTIMATE_POSE, None

    def counters(self) -> dict[str, object]:
        """Samples kept and dropped, over every robot, and how fast the simulators'
        clocks ran by each robot's (1: real time).
        """
        with self._lock:
            tracks = [*self.truths.values(), *self.tracks.values()]
            return {
                "pose_samples": sum(len(t.rows) for t in tracks),
                "pose_samples_dropped": sum(t.dropped for t in tracks),
                "simulator_clock_rate": dict(self.clock_rates),
            }


def observed_robots(
    observed: tuple[str, ...],
    ids: tuple[str, ...],
    *,
    fleet: str,
    clock: str,
    epoch_s: float | None,
    bounds: FleetBounds,
) -> ObservedRobots | None:
    """The robots of `ids` to record rather than simulate (None: every robot is
    simulated); ConfigError for a robot not in the scenario, or without the wall clock
    and epoch they keep.
    """
    if not observed:
        return None
    unknown = sorted(set(observed) - set(ids))
    if unknown:
        raise ConfigError(f"robots to observe {unknown} are not in the scenario")
    if clock != "realtime" or epoch_s is None:
        raise ConfigError(
            "robots that move on their own keep the wall clock: observing them needs "
            "--clock realtime and the run's --epoch"
        )
    chosen = tuple(r for r in ids if r in observed)
    return ObservedRobots(chosen, fleet=fleet, epoch_s=epoch_s, bounds=bounds)
