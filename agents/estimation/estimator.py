"""One robot's pose estimator: the filter of `phalanx.agents.estimation.ekf` run over a
short history, so a measurement that arrives late is applied at the time it was taken.

Every control step brings one odometry reading; the increment since the last one is a
node of the history (its arc, its duration, the measurements taken within it, the belief
at its end). A new measurement goes into the node whose interval holds its stamp; the
filter then goes back to the belief before the earliest node that changed and replays
from there: each node's arc in pieces, cut at its measurements' stamps, each measurement
applied where it was taken (buffer and replay). A measurement older than the history
(`history_s`) is dropped and counted; one stamped a little ahead of the last odometry
(clocks of two computers) is applied at the last odometry's time. A pose fix counts as
uncertain by the robot's motion over the time its stamp may be off the odometry's
(`stamp_std_s` of its source, and how far ahead it was).

A filter that refused every pose fix for `RELOCALISE_AFTER_S` is lost, not the positioning
system: sure of a pose its odometry carried off (a fast turn at the start, a wheel
slipping), it would refuse every fix to come and drive on odometry alone. It then takes
the newest fix as its belief, with that fix's covariance (what a pose measurement says
given no prior), and replays from there; counted as `fix_relocalised`. A lone outlier, or
a burst of them shorter than that, is still refused.

Sources: absolute pose fixes (`PoseFix`: motion capture, an overhead camera) and
relative measurements of the robot this one tracks (`RelativeFix`: a camera on a
fiducial marker), which, with that robot's published estimate and covariance, tell where
this robot is in the frame that robot's estimate lives in: a follower with relative
sensing keeps its slot in its leader's frame, whether or not the leader knows where it
is in the world.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

from phalanx.agents.estimation.ekf import Belief, ProcessNoise, predict, update_pose, wrap
from phalanx.agents.estimation.relative import as_pose_fix, update_range_bearing
from phalanx.core.fixes import Cov6, PoseFix, RelativeFix
from phalanx.core.frozen import quick_init
from phalanx.core.geometry import Pose2D, integrate_unicycle
from phalanx.core.localisation import LocalisationConfig
from phalanx.core.peers import PeerState
from phalanx.core.robot import Odometry

# A measurement stamped this far ahead of the last odometry is applied at its time.
AHEAD_TOLERANCE_S = 0.25
# Odometry increments shorter than this give no rate for a fix's timing noise.
MIN_RATE_SPAN_S = 1e-3
# Stamps this close are one instant: a measurement at an odometry reading's time goes into
# the increment that ends there, whether step k's time is k * dt (one process) or a sum
# of dt (another), which differ in the last bit.
SAME_INSTANT_S = 1e-9
# A robot that had an absolute fix this recently lives in the world frame: relative
# measurements (which tie it to another robot's estimate) wait until the fixes stop.
ABSOLUTE_FRESH_S = 0.5
# A filter that refused every pose fix this long (by the fixes' stamps) takes the newest.
RELOCALISE_AFTER_S = 0.5
# How far the leader's published estimate may be carried forward or back to the instant
# of a relative measurement; the extra uncertainty per second of it (m, rad).
MAX_LEADER_AGE_S = 1.0
LEADER_DRIFT_STD_MPS = 0.02
LEADER_DRIFT_STD_RADPS = 0.02


@quick_init
@dataclass(frozen=True, slots=True)
class Estimate:
    """A robot's pose estimate at `stamp_s` and its covariance (upper triangle)."""

    pose: Pose2D
    cov: Cov6
    stamp_s: float


@dataclass(frozen=True, slots=True)
class _Taken:
    """A measurement as the history keeps it: a pose fix (`reset`: taken as the belief,
    the filter being lost), or a relative measurement with the tracked robot's state as
    it was known when the measurement arrived (so a replay gives the same result).
    """

    stamp_s: float
    fix: PoseFix | None = None
    relative: RelativeFix | None = None
    lead: PeerState | None = None
    reset: bool = False


@dataclass(slots=True)
class _Node:
    t_s: float
    ds_m: float
    dth_rad: float
    taken: list[_Taken]
    belief: Belief
    after: list[Belief] = field(default_factory=list)  # the belief after each of `taken`


@dataclass
class EstimatorStats:
    """What the estimator did with its measurements (counts per outcome)."""

    counts: Counter[str] = field(default_factory=Counter)


def process_noise(config: LocalisationConfig, track_m: float) -> ProcessNoise:
    """The filter's process noise from the scenario's odometry error model."""
    odo = config.odometry
    return ProcessNoise(
        track_m=track_m,
        scale_var=odo.scale_std_frac**2,
        walk_var_per_m=odo.walk_std_m**2,
        # slip: a wheel loses U(0, max) of its travel, `slip_per_m` times a metre
        slip_var_per_m3=odo.slip_per_m * odo.slip_max_frac**2 / 3.0,
        floor_var_m2ps=odo.floor_std_m**2,
        floor_var_rad2ps=math.radians(odo.floor_std_deg) ** 2,
    )


def arc_of(before: Pose2D, after: Pose2D) -> tuple[float, float]:
    """The arc (signed length m, turn rad) that takes `before` to `after`."""
    local = before.relative(after)
    dth = wrap(local.theta_rad)
    half = 0.5 * dth
    chord = math.hypot(local.x_m, local.y_m)
    sign = -1.0 if local.x_m < 0.0 else 1.0
    stretch = half / math.sin(half) if abs(half) > 1e-9 else 1.0
    return sign * chord * stretch, dth


class PoseEstimator:
    """Fuses one robot's odometry with its pose fixes and relative measurements."""

    def __init__(self, config: LocalisationConfig, *, track_m: float, robot_id: str) -> None:
        self.config = config
        self.robot_id = robot_id
        self.noise = process_noise(config, track_m)
        self.stats = EstimatorStats()
        self._nodes: deque[_Node] = deque()
        self._last_odometry: Pose2D | None = None
        self._last_fix_s = -math.inf
        self._last_fused_s = -math.inf  # the newest fix fused (or the first one taken)
        self._min_fix_gap_s = 0.0
        if config.mocap is not None and config.mocap.fuse_hz < config.mocap.rate_hz:
            # (a hair under the period: stamps k / rate are not exact in floating point)
            self._min_fix_gap_s = 0.999 / config.mocap.fuse_hz
        self._frame_of: PeerState | None = None  # whose frame the estimate lives in
        stamp_std_s = config.mocap.stamp_std_s if config.mocap is not None else 0.0
        self._stamp_var_s2 = stamp_std_s * stamp_std_s

    def step(
        self,
        odometry: Odometry,
        *,
        fixes: tuple[PoseFix, ...] = (),
        relative: tuple[RelativeFix, ...] = (),
        anchors: Mapping[str, PeerState] | None = None,
    ) -> Estimate:
        """The estimate at `odometry.stamp_s`, given this step's odometry and whatever
        measurements arrived since the last step (any stamps, any order). `anchors`: the
        latest states of the robots whose relative measurements this robot may fuse
        (`phalanx.agents.estimation.landmarks`); a measurement of any other is counted
        and left out.
        """
        self._advance(odometry)
        taken = self._select(fixes, relative, anchors or {})
        first = (len(self._nodes) - 1, 0)
        for item in taken:
            place = self._place(item)
            if place is not None:
                first = min(first, place)
        self._replay(*first)
        if self._last_fix_s - self._last_fused_s >= RELOCALISE_AFTER_S:
            self._relocalise()
        self._trim()
        b = self._nodes[-1].belief
        return Estimate(Pose2D(b.x, b.y, b.th), self.published_cov(b), odometry.stamp_s)

    # --- the history -------------------------------------------------------------------

    def _advance(self, odometry: Odometry) -> None:
        pose, t_s = odometry.pose, odometry.stamp_s
        if self._last_odometry is None or not self._nodes:
            sm, sr = self.config.initial_std_m, math.radians(self.config.initial_std_deg)
            p0 = (sm * sm, 0.0, 0.0, sm * sm, 0.0, sr * sr)
            self._nodes.append(
                _Node(t_s, 0.0, 0.0, [], Belief(pose.x_m, pose.y_m, pose.theta_rad, p0))
            )
        else:
            ds, dth = arc_of(self._last_odometry, pose)
            last = self._nodes[-1]
            if t_s <= last.t_s:  # the same instant again: fold the motion into it
                t_s = last.t_s + 1e-9
            self._nodes.append(_Node(t_s, ds, dth, [], last.belief))
        self._last_odometry = pose

    def _select(
        self,
        fixes: tuple[PoseFix, ...],
        relative: tuple[RelativeFix, ...],
        anchors: Mapping[str, PeerState],
    ) -> list[_Taken]:
        count = self.stats.counts
        taken = []
        for fix in sorted(fixes, key=lambda f: f.stamp_s):
            if fix.stamp_s - self._last_fix_s < self._min_fix_gap_s:
                count["fix_thinned"] += 1
                continue
            if self._last_fused_s == -math.inf:  # (the time since fixes first came)
                self._last_fused_s = fix.stamp_s
            self._last_fix_s = fix.stamp_s
            taken.append(_Taken(fix.stamp_s, fix=fix))
        for rel in relative:
            anchor = anchors.get(rel.target_id)
            if anchor is None:
                count["relative_not_anchor"] += 1
            elif abs(rel.stamp_s - self._last_fix_s) < ABSOLUTE_FRESH_S:
                count["relative_while_fixed"] += 1
            else:
                taken.append(_Taken(rel.stamp_s, relative=rel, lead=anchor))
        return taken

    def _place(self, item: _Taken) -> tuple[int, int] | None:
        """Where `item` goes: (node, position among its measurements), or None."""
        nodes, count = self._nodes, self.stats.counts
        if item.stamp_s > nodes[-1].t_s + AHEAD_TOLERANCE_S or not math.isfinite(item.stamp_s):
            count["ahead_dropped"] += 1
            return None
        if item.stamp_s <= nodes[0].t_s:
            count["late_dropped"] += 1
            return None
        index = len(nodes) - 1
        while index > 0 and nodes[index - 1].t_s >= item.stamp_s - SAME_INSTANT_S:
            index -= 1
        taken = nodes[index].taken
        position = len(taken)
        while position > 0 and taken[position - 1].stamp_s > item.stamp_s:
            position -= 1
        taken.insert(position, item)
        if index < len(nodes) - 1:
            count["replayed"] += 1
        return max(index, 1), position if index >= 1 else 0

    def _replay(self, first: int, position: int) -> None:
        """Recompute the beliefs from node `first`'s measurement `position` on (the belief
        just before it is kept: only what the new measurements change is done again).
        """
        nodes = self._nodes
        for i in range(first, len(nodes)):
            node, start = nodes[i], nodes[i - 1].t_s
            span = node.t_s - start
            k = position if i == first else 0
            belief, done = nodes[i - 1].belief, 0.0
            if k > 0:
                belief, done = node.after[k - 1], _fraction(node.taken[k - 1], start, span)
            del node.after[k:]
            for item in node.taken[k:]:
                frac = _fraction(item, start, span)
                belief = self._apply(self._piece(belief, node, frac - done, span), item, node, span)
                done = frac
                node.after.append(belief)
            node.belief = self._piece(belief, node, 1.0 - done, span)

    def _piece(self, belief: Belief, node: _Node, frac: float, span_s: float) -> Belief:
        if frac <= 0.0:
            return belief
        return predict(belief, node.ds_m * frac, node.dth_rad * frac, span_s * frac, self.noise)

    def _relocalise(self) -> None:
        """Take the newest pose fix in the history as the belief and replay from it."""
        for i in range(len(self._nodes) - 1, 0, -1):
            taken = self._nodes[i].taken
            for j in range(len(taken) - 1, -1, -1):
                if taken[j].fix is not None:
                    taken[j] = replace(taken[j], reset=True)
                    self.stats.counts["fix_relocalised"] += 1
                    self._replay(i, j)
                    return

    def _trim(self) -> None:
        nodes = self._nodes
        horizon = nodes[-1].t_s - self.config.history_s
        while len(nodes) > 2 and nodes[1].t_s < horizon:
            nodes.popleft()

    # --- measurements ------------------------------------------------------------------

    def _apply(self, belief: Belief, item: _Taken, node: _Node, span_s: float) -> Belief:
        if item.fix is not None:
            fix = item.fix
            r = self._fix_noise(fix, belief.th, node, span_s)
            if item.reset:
                out: Belief | None = Belief(fix.x_m, fix.y_m, fix.theta_rad, r)
            else:
                out = update_pose(belief, (fix.x_m, fix.y_m, fix.theta_rad), r, self.config.gate)
            if out is not None:
                self._frame_of = None  # back in the world frame
                self._last_fused_s = max(self._last_fused_s, fix.stamp_s)
            return self._count(out, belief, "fix")
        if item.relative is None or item.lead is None:  # (never: `_select` pairs them)
            return belief
        return self._count(self._relative(belief, item.relative, item.lead), belief, "relative")

    def _fix_noise(self, fix: PoseFix, heading: float, node: _Node, span_s: float) -> Cov6:
        """The fix's covariance, and the robot's motion over the time its stamp may be off
        the odometry's timeline (`stamp_std_s`, and how far past the latest odometry it
        lies when it is applied there): a fix taken during a fast turn at a stamp a few
        milliseconds off says the heading is a degree elsewhere.
        """
        var_m, var_rad = fix.std_m**2, fix.std_rad**2
        ahead_s = max(0.0, fix.stamp_s - node.t_s)
        var_s = self._stamp_var_s2 + ahead_s * ahead_s
        if var_s == 0.0 or span_s < MIN_RATE_SPAN_S:
            return (var_m, 0.0, 0.0, var_m, 0.0, var_rad)
        sd_s = math.sqrt(var_s)
        along, turn = node.ds_m / span_s * sd_s, node.dth_rad / span_s * sd_s
        jx, jy = along * math.cos(heading), along * math.sin(heading)
        return (
            var_m + jx * jx,
            jx * jy,
            jx * turn,
            var_m + jy * jy,
            jy * turn,
            var_rad + turn * turn,
        )

    def _count(self, out: Belief | None, before: Belief, kind: str) -> Belief:
        self.stats.counts[f"{kind}_fused" if out is not None else f"{kind}_gated"] += 1
        return out if out is not None else before

    def _relative(self, b: Belief, rel: RelativeFix, lead: PeerState) -> Belief | None:
        """Range, bearing (and relative heading) of the tracked robot, whose pose at the
        measurement's instant is its published estimate carried there along its twist
        (the carrying's uncertainty added to the sensor's noise).

        The update leaves the tracked robot's own covariance out on purpose: the
        measurement puts this robot where it is relative to that robot's estimate, so its
        estimate lives in the frame of the tracked robot's (what keeping a slot needs),
        and the covariance it publishes adds the tracked robot's, carried over
        (`published_cov`).
        """
        age_s = max(-MAX_LEADER_AGE_S, min(MAX_LEADER_AGE_S, rel.stamp_s - lead.stamp_s))
        other = integrate_unicycle(lead.pose, lead.twist, age_s)
        carried = _carried(abs(age_s), lead.v_mps)
        if rel.heading_rad is None:
            out = update_range_bearing(b, rel, other, carried, self.config.gate)
        else:
            z, r = as_pose_fix(rel, other, carried)
            out = update_pose(b, z, r, self.config.gate)
        if out is not None:
            self._frame_of = lead
        return out

    def published_cov(self, belief: Belief) -> Cov6:
        """The covariance to publish: the filter's own, plus, while this robot's estimate
        lives in the frame of the robot it measures (relative sensing), that robot's
        covariance carried to this robot as if rigidly attached to it.
        """
        lead = self._frame_of
        if lead is None or len(lead.cov) != 6:
            return belief.p
        xx, xy, xt, yy, yt, tt = lead.cov
        a, c = -(belief.y - lead.y_m), belief.x - lead.x_m  # T = [[1,0,a],[0,1,c],[0,0,1]]
        add = (
            xx + 2 * a * xt + a * a * tt,
            xy + a * yt + c * xt + a * c * tt,
            xt + a * tt,
            yy + 2 * c * yt + c * c * tt,
            yt + c * tt,
            tt,
        )
        return tuple(p + q for p, q in zip(belief.p, add, strict=True))  # type: ignore[return-value]


def _fraction(item: _Taken, start_s: float, span_s: float) -> float:
    """Where in its node's interval a measurement was taken (0: its start, 1: its end)."""
    return min(1.0, max(0.0, (item.stamp_s - start_s) / span_s)) if span_s > 0 else 1.0


def _carried(age_s: float, v_mps: float) -> tuple[float, float, float]:
    """Variances (x, y, theta) a published pose gains carried `age_s` along its twist."""
    pos = (LEADER_DRIFT_STD_MPS * age_s) ** 2 + (0.02 * v_mps * age_s) ** 2
    return pos, pos, (LEADER_DRIFT_STD_RADPS * age_s) ** 2
