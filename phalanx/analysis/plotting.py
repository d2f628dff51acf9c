"""Drawing a large fleet: lines as collections, decimated to about the pixels drawn.

Up to `LEGEND_MAX` robots, the figures of `phalanx.analysis.figures` give each robot its
own line and legend entry; beyond, one `LineCollection` per kind of line (an artist per
robot costs matplotlib milliseconds each, a thousand of them tens of seconds).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection

from phalanx.core.runlog import RunLog

COLOURS = ("tab:red", "tab:blue", "tab:green", "tab:purple", "tab:orange", "tab:brown")
# More lines than this are drawn as collections, without a legend entry each.
LEGEND_MAX = 12
POINTS_PER_LINE = 2000
FloatArray = npt.NDArray[np.float64]


def decimated(x: FloatArray, y: FloatArray) -> FloatArray:
    """(points, 2) of a line, every k-th point kept (and the last) beyond POINTS_PER_LINE."""
    k = max(1, math.ceil(len(x) / POINTS_PER_LINE))
    keep = np.r_[np.arange(0, len(x), k), len(x) - 1] if k > 1 and len(x) else slice(None)
    return np.column_stack([np.asarray(x, dtype=float)[keep], np.asarray(y, dtype=float)[keep]])


def collection(ax: Axes, lines: list[FloatArray], offset: int = 0, **style: Any) -> None:
    """Many lines as one artist, coloured in turn."""
    colours = [COLOURS[(i + offset) % len(COLOURS)] for i in range(len(lines))]
    ax.add_collection(LineCollection(lines, colors=colours, **style))
    ax.autoscale_view()


def fleet_note(ax: Axes, n: int) -> None:
    """Say how many robots the lines are (there is no legend)."""
    ax.text(0.01, 0.99, f"{n} robots", transform=ax.transAxes, va="top", fontsize=8)


def fleet_trajectories(ax: Axes, log: RunLog) -> None:
    """Every robot's path (reverse dashed), start and end marked, as collections."""
    traces = list(log.traces.values())
    collection(ax, [decimated(tr.x_m, tr.y_m) for tr in traces], lw=0.8)
    backs = [decimated(tr.x_m, np.where(tr.direction < 0, tr.y_m, np.nan)) for tr in traces]
    collection(ax, backs, lw=2.0, linestyles="--")
    for k, marker in ((0, "o"), (-1, "s")):
        xy = np.array([(tr.x_m[k], tr.y_m[k]) for tr in traces])
        ax.scatter(xy[:, 0], xy[:, 1], s=6, marker=marker, c="k", zorder=3)
    fleet_note(ax, len(traces))
