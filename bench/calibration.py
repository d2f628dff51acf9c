"""A fixed calibration workload every benchmark times in the same run, so a figure taken
on one machine can be checked on another: each figure is printed beside its ratio to the
calibration (`cal`), which moves with the machine's speed and load the way phalanx's own
work does. The workload is the mix a control step is made of: plain-Python float
arithmetic and attribute access, and numpy calls on small arrays.

    from calibration import Calibration
    cal = Calibration.measure()          # prints the workload's time and the load
    print(cal.ratio(seconds))            # "12.3 cal"
"""

from __future__ import annotations

import math
import statistics
import time
from dataclasses import dataclass

import numpy as np

REPEATS = 7


def _workload() -> float:
    """About 40 ms on a 2-core EPYC: 60 000 Python float steps, 3 000 small numpy calls."""
    acc = 0.0
    x, v = 0.0, 0.1
    for i in range(60_000):
        v = v + 1e-4 * math.sin(i * 1e-3)
        x = x + v * 0.01
        acc += abs(x) if x < 1e6 else 0.0
    a = np.linspace(0.0, 1.0, 48)
    for _ in range(1_000):
        a = np.minimum(a * 1.0001, 2.0)
        acc += float(np.hypot(a, a).max())
    return acc


def load() -> str:
    """The 1, 5 and 15 minute load averages (other processes sharing the cores)."""
    try:
        with open("/proc/loadavg", encoding="ascii") as f:
            return " ".join(f.read().split()[:3])
    except OSError:
        return "n/a"


@dataclass(frozen=True)
class Calibration:
    """The calibration workload's median time (s) in this run."""

    seconds: float

    @classmethod
    def measure(cls, *, quiet: bool = False) -> Calibration:
        """Time the workload `REPEATS` times and keep the median."""
        _workload()  # warm up
        times = []
        for _ in range(REPEATS):
            started = time.perf_counter()
            _workload()
            times.append(time.perf_counter() - started)
        cal = cls(statistics.median(times))
        if not quiet:
            print(f"calibration: {1e3 * cal.seconds:.1f} ms (1 cal), load {load()}")
        return cal

    def ratio(self, seconds: float) -> float:
        """`seconds` in calibration units."""
        return seconds / self.seconds

    def cal(self, seconds: float) -> str:
        """`seconds` in calibration units, for printing."""
        return f"{self.ratio(seconds):.3g} cal"
