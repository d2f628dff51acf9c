"""Simulated external positioning (motion capture, an overhead camera): every tracked
robot's pose sampled at the system's rate, with noise, a share of samples lost, and
delivered `latency_s` after it was taken, stamped with the instant it was taken.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
import numpy.typing as npt

from phalanx.core.fixes import PoseFix
from phalanx.core.localisation import MocapSource

FloatArray = npt.NDArray[np.float64]


class MocapSim:
    """Pose fixes of the robots `source` tracks, seeded."""

    def __init__(self, source: MocapSource, *, seed: int) -> None:
        self.source = source
        self.rng = np.random.default_rng([seed, 0x30CA])
        self.period_s = 1.0 / source.rate_hz
        self.std_rad = math.radians(source.std_deg)
        self._next_k = 0
        self._tracked: list[bool] = []
        self._queues: list[deque[tuple[float, PoseFix]]] = []
        self.lost = 0

    def add_robot(self, robot_id: str) -> None:
        """A robot of the world (tracked if the source covers it)."""
        self._tracked.append(self.source.tracks(robot_id))
        self._queues.append(deque())

    def sample(self, t0_s: float, dt_s: float, before: FloatArray, after: FloatArray) -> None:
        """Take the samples due in (t0, t0 + dt] from the robots' poses (n x 3) at both
        ends of that interval (interpolated between them).
        """
        while (t_s := self._next_k * self.period_s) <= t0_s + dt_s + 1e-12:
            self._next_k += 1
            if t_s <= t0_s + 1e-12 and self._next_k > 1:
                continue
            frac = min(1.0, max(0.0, (t_s - t0_s) / dt_s)) if dt_s > 0 else 1.0
            self._take(t_s, between(before, after, frac))

    def _take(self, t_s: float, poses: FloatArray) -> None:
        n, src = len(poses), self.source
        noise = self.rng.normal(0.0, 1.0, (n, 3)) * (src.std_m, src.std_m, self.std_rad)
        kept = self.rng.random(n) >= src.dropout
        for i in range(n):
            if not self._tracked[i]:
                continue
            if not kept[i]:
                self.lost += 1
                continue
            x, y, th = poses[i] + noise[i]
            fix = PoseFix(t_s, float(x), float(y), _wrap(float(th)), src.std_m, self.std_rad)
            self._queues[i].append((t_s + src.latency_s, fix))

    def take(self, index: int, now_s: float) -> tuple[PoseFix, ...]:
        """Robot `index`'s fixes that have arrived by `now_s`."""
        queue, out = self._queues[index], []
        while queue and queue[0][0] <= now_s + 1e-9:
            out.append(queue.popleft()[1])
        return tuple(out)


def between(before: FloatArray, after: FloatArray, frac: float) -> FloatArray:
    """Poses (n x 3) a share `frac` of the way from `before` to `after` (headings the short way)."""
    turn = np.mod(after[:, 2] - before[:, 2] + np.pi, 2 * np.pi) - np.pi
    out = before + frac * (after - before)
    out[:, 2] = before[:, 2] + frac * turn
    return out


def _wrap(angle_rad: float) -> float:
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi
