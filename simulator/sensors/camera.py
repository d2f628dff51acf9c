"""A simulated camera reading the fiducial markers on other robots: range, bearing and
relative heading of every robot whose marker it sees.

A marker is seen when its robot is inside the camera's field of view (about the axis the
camera is mounted along), between the minimum and maximum range, and the line of sight
from camera to marker crosses no other robot and no obstacle; not during a scripted
`markers_hidden` event; not when the frame is lost (`dropout`). Noise grows with range
(range: a share of it; relative heading: its std times the range over 1 m, at least
the std), bearing noise is constant. Frames come at the camera's rate and reach the robot
`latency_s` after they were taken, stamped with the instant they were taken. The marker
sits above the robot's centre on every side (a box of four), so the side it shows does
not matter.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Mapping

import numpy as np
import numpy.typing as npt

from phalanx.core.fixes import RelativeFix
from phalanx.core.localisation import MarkerSource
from phalanx.simulator.sensors.mocap import between

FloatArray = npt.NDArray[np.float64]
Obstacles = tuple[FloatArray, tuple[FloatArray, FloatArray, FloatArray, FloatArray]]
HiddenCheck = Callable[[str, float], bool]


def _wrap(angle: FloatArray | float) -> FloatArray:
    return np.asarray(np.mod(np.asarray(angle) + np.pi, 2 * np.pi) - np.pi, dtype=np.float64)


def sight_blocked(
    ax: float, ay: float, bx: float, by: float, circles: FloatArray, edges: tuple[FloatArray, ...]
) -> bool:
    """Whether the segment a-b passes through a circle (rows x, y, r) or crosses an edge."""
    dx, dy = bx - ax, by - ay
    length2 = max(dx * dx + dy * dy, 1e-12)
    if len(circles):
        t = np.clip(((circles[:, 0] - ax) * dx + (circles[:, 1] - ay) * dy) / length2, 0.0, 1.0)
        gap = np.hypot(ax + t * dx - circles[:, 0], ay + t * dy - circles[:, 1])
        if bool(np.any(gap < circles[:, 2])):
            return True
    ex0, ey0, ex1, ey1 = edges
    if len(ex0) == 0:
        return False
    ux, uy = ex1 - ex0, ey1 - ey0
    denom = dx * uy - dy * ux
    ok = np.abs(denom) > 1e-12
    safe = np.where(ok, denom, 1.0)
    s = ((ex0 - ax) * uy - (ey0 - ay) * ux) / safe
    u = ((ex0 - ax) * dy - (ey0 - ay) * dx) / safe
    return bool(np.any(ok & (s >= 0.0) & (s <= 1.0) & (u >= 0.0) & (u <= 1.0)))


class MarkerCameraSim:
    """The cameras of the robots `source` equips, seeded."""

    def __init__(
        self,
        source: MarkerSource,
        *,
        seed: int,
        robot_radius_m: float,
        obstacles: Obstacles,
        mounts_rad: Mapping[str, float],
        hidden: HiddenCheck,
    ) -> None:
        self.source = source
        self.rng = np.random.default_rng([seed, 0xCA3])
        self.period_s = 1.0 / source.rate_hz
        self.radius_m = robot_radius_m
        self.circles, self.edges = obstacles
        self.mounts_rad = dict(mounts_rad)
        self.hidden = hidden
        self._ids: list[str] = []
        self._queues: list[deque[tuple[float, RelativeFix]]] = []
        self._next_k = 0
        self.frames = 0
        self.seen = 0

    def add_robot(self, robot_id: str) -> None:
        """A robot of the world (with a camera if `mounts_rad` gives it one)."""
        self._ids.append(robot_id)
        self._queues.append(deque())

    def sample(self, t0_s: float, dt_s: float, before: FloatArray, after: FloatArray) -> None:
        """Take the frames due in (t0, t0 + dt] from the robots' poses (n x 3) at both ends
        of that interval (interpolated between them).
        """
        while (t_s := self._next_k * self.period_s) <= t0_s + dt_s + 1e-12:
            self._next_k += 1
            if t_s > t0_s + 1e-12 or self._next_k == 1:
                frac = min(1.0, max(0.0, (t_s - t0_s) / dt_s)) if dt_s > 0 else 1.0
                self._frame(t_s, between(before, after, frac))

    def _frame(self, t_s: float, poses: FloatArray) -> None:
        for i, rid in enumerate(self._ids):
            mount = self.mounts_rad.get(rid)
            if mount is None or self.hidden(rid, t_s):
                continue
            self.frames += 1
            if self.rng.random() < self.source.dropout:
                continue
            for fix in self._seen_from(i, t_s, poses, mount):
                self.seen += 1
                self._queues[i].append((t_s + self.source.latency_s, fix))

    def _seen_from(self, i: int, t_s: float, poses: FloatArray, mount: float) -> list[RelativeFix]:
        src = self.source
        x, y, th = poses[i]
        dx, dy = poses[:, 0] - x, poses[:, 1] - y
        rng = np.hypot(dx, dy)
        bearing = _wrap(np.arctan2(dy, dx) - th)
        visible = (np.abs(_wrap(bearing - mount)) <= src.half_fov_rad) & (rng >= src.min_range_m)
        visible &= rng <= src.max_range_m
        visible[i] = False
        out = []
        for j in np.flatnonzero(visible).tolist():
            if self._occluded(i, j, poses):
                continue
            r = float(rng[j])
            std_r = src.range_std_frac * r
            std_b = math.radians(src.bearing_std_deg)
            std_h = math.radians(src.heading_std_deg) * max(1.0, r)
            z = self.rng.normal(0.0, 1.0, 3)
            out.append(
                RelativeFix(
                    stamp_s=t_s,
                    target_id=self._ids[j],
                    range_m=max(0.0, r + std_r * z[0]),
                    bearing_rad=float(_wrap(bearing[j] + std_b * z[1])),
                    std_range_m=std_r,
                    std_bearing_rad=std_b,
                    heading_rad=float(_wrap(poses[j, 2] - th + std_h * z[2])),
                    std_heading_rad=std_h,
                )
            )
        return out

    def _occluded(self, i: int, j: int, poses: FloatArray) -> bool:
        others = np.ones(len(poses), dtype=bool)
        others[[i, j]] = False
        robots = np.column_stack(
            [poses[others, 0], poses[others, 1], np.full(int(others.sum()), self.radius_m)]
        )
        circles = np.vstack([self.circles, robots]) if len(robots) else self.circles
        a, b = poses[i], poses[j]
        return sight_blocked(
            float(a[0]), float(a[1]), float(b[0]), float(b[1]), circles, self.edges
        )

    def take(self, index: int, now_s: float) -> tuple[RelativeFix, ...]:
        """Robot `index`'s measurements that have arrived by `now_s`."""
        queue, out = self._queues[index], []
        while queue and queue[0][0] <= now_s + 1e-9:
            out.append(queue.popleft()[1])
        return tuple(out)
