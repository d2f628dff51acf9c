"""Figures of a run (PNG, PDF or SVG), the counterparts of the paper's figures 4b, 5, 6 and 7 (its
figure 4a, the state machine, is drawn by `phalanx fsm`: `phalanx.analysis.fsm_picture`).

fig4b: behaviour state over time, with who led; fig5: trajectories (and obstacles) with the
reverse phase marked; fig6: linear and angular separations against their desired
values; fig7: velocity profiles against the run's limits; and the dead-end escape
(`deadend_escape`: the way in and back out, and the errors while reversing).

Figures scale with the fleet: up to `LEGEND_MAX` robots each gets its own line and a
legend entry; a larger fleet's lines go into one `LineCollection` per kind, each line
decimated to about `POINTS_PER_LINE` points (more than the pixels it is drawn across),
so a 1000-robot run draws in seconds (`phalanx.analysis.plotting`).

Drawn for a paper: every legend sits outside the axes (right of them), every robot has
a line style of its own besides its colour (paths that overlap stay told apart), the
titles name the scenario and the controller, and the trajectories' axes fit the course
at equal aspect.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import matplotlib as mpl

mpl.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import numpy.typing as npt
from matplotlib.axes import Axes
from matplotlib.figure import Figure, FigureBase
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, Patch, Polygon

from phalanx.analysis.estimation import NEES_BAND, nees, pose_errors
from phalanx.analysis.figure_files import DEFAULT_DPI as DEFAULT_DPI
from phalanx.analysis.figure_files import DPI_MAX as DPI_MAX
from phalanx.analysis.figure_files import DPI_MIN as DPI_MIN
from phalanx.analysis.figure_files import ESTIMATION_FIGURE as ESTIMATION_FIGURE
from phalanx.analysis.figure_files import FIGURE_FILES
from phalanx.analysis.figure_files import FORMATS as FORMATS
from phalanx.analysis.figure_files import PAPER_FIGURE as PAPER_FIGURE
from phalanx.analysis.figure_files import FigureFormat as FigureFormat
from phalanx.analysis.figure_files import figure_name as figure_name
from phalanx.analysis.metrics import (
    error_series,
    is_follower,
    leader_direction,
    leader_series,
    phase_masks,
    tracked_series,
)
from phalanx.analysis.plotting import (
    COLOURS,
    LEGEND_MAX,
    collection,
    decimated,
    fleet_note,
    fleet_trajectories,
)
from phalanx.core.limits import KinematicLimits
from phalanx.core.runlog import RunLog
from phalanx.core.scenarios import resolve_world
from phalanx.core.states import State

# A style per robot besides its colour (no plain dotted: that marks desired values).
LINESTYLES: tuple[str | tuple[int, tuple[int, ...]], ...] = (
    "-",
    "--",
    "-.",
    (0, (1, 1)),
    (0, (5, 1, 1, 1, 1, 1)),
    (0, (8, 2)),
)
# Room for the legend right of the axes, in inches.
LEGEND_ROOM_IN = 1.6


def _style(i: int) -> dict[str, Any]:
    """Colour and line style of the i-th robot."""
    return {"color": COLOURS[i % len(COLOURS)], "ls": LINESTYLES[i % len(LINESTYLES)]}


Titled = Callable[[str], str]  # a panel's title from what it shows


def _title(log: RunLog, what: str) -> str:
    return f"{log.scenario.name} / {log.scenario.controller.kind}: {what}"


def _titled(log: RunLog) -> Titled:
    """Titles naming the scenario and the controller (a figure of its own)."""
    return lambda what: _title(log, what)


def _legend_outside(fig: FigureBase, handles: list[Any]) -> None:
    """One legend for the whole figure, right of every axes (the figure's layout must be
    constrained, which makes room for it).
    """
    fig.legend(handles=handles, loc="outside right upper", fontsize=9)


def _followers(log: RunLog) -> list[str]:
    return [r for r in log.formation.robot_ids if is_follower(log, r)]


def _reverse_spans(log: RunLog) -> list[tuple[float, float]]:
    direction = leader_direction(log)
    spans, start = [], None
    for k, d in enumerate(direction):
        if d < 0 and start is None:
            start = float(log.t_s[k])
        if d > 0 and start is not None:
            spans.append((start, float(log.t_s[k])))
            start = None
    if start is not None:
        spans.append((start, float(log.t_s[-1])))
    return spans


def _key(log: RunLog, line: tuple[str, str]) -> list[Any]:
    """Legend entries for a black line of style `line[1]` meaning `line[0]`, and for the
    grey reverse shading if the run reversed.
    """
    label, ls = line
    out: list[Any] = [Line2D([], [], color="k", ls=ls, lw=1, label=label)]
    if _reverse_spans(log):
        out.append(Patch(color="0.85", label="reverse"))
    return out


def _shade(ax: Axes, log: RunLog) -> None:
    for i, (a, b) in enumerate(_reverse_spans(log)):
        ax.axvspan(a, b, color="0.85", label="reverse" if i == 0 else None)


def draw_world(ax: Axes, log: RunLog) -> None:
    """The run's obstacles (a seeded field included) in grey."""
    world = resolve_world(log.scenario.world)
    for c in world.circles:
        ax.add_patch(Circle((c.x_m, c.y_m), c.radius_m, color="0.65", zorder=0))
    for poly in world.polygons:
        ax.add_patch(Polygon(poly.vertices_m, closed=True, color="0.65", zorder=0))
    for x, y in log.scenario.navigation.waypoints:
        ax.plot(x, y, "k*", ms=12, zorder=3)


def _extent(log: RunLog) -> tuple[float, float, float, float]:
    """(x min, x max, y min, y max) of the paths, obstacles and waypoints, with a margin."""
    xs = [np.zeros(0)] + [np.asarray(tr.x_m, dtype=float) for tr in log.traces.values()]
    ys = [np.zeros(0)] + [np.asarray(tr.y_m, dtype=float) for tr in log.traces.values()]
    world = resolve_world(log.scenario.world)
    for c in world.circles:
        xs.append(np.array([c.x_m - c.radius_m, c.x_m + c.radius_m]))
        ys.append(np.array([c.y_m - c.radius_m, c.y_m + c.radius_m]))
    for poly in world.polygons:
        xs.append(np.array([v[0] for v in poly.vertices_m], dtype=float))
        ys.append(np.array([v[1] for v in poly.vertices_m], dtype=float))
    for wx, wy in log.scenario.navigation.waypoints:
        xs.append(np.array([wx], dtype=float))
        ys.append(np.array([wy], dtype=float))
    x, y = np.concatenate(xs), np.concatenate(ys)
    x, y = x[np.isfinite(x)], y[np.isfinite(y)]
    x0, x1 = (float(x.min()), float(x.max())) if x.size else (0.0, 1.0)
    y0, y1 = (float(y.min()), float(y.max())) if y.size else (0.0, 1.0)
    margin = 0.05 * max(x1 - x0, y1 - y0, 1.0)
    return x0 - margin, x1 + margin, y0 - margin, y1 + margin


def _map_size(extent: tuple[float, float, float, float], legend: bool) -> tuple[float, float]:
    """A figure size (inches) whose axes have about the course's shape: 7 in wide, as
    tall as the course at equal aspect within 2.5-9 in, plus the title, labels and legend.
    """
    x0, x1, y0, y1 = extent
    height = min(9.0, max(2.5, 7.0 * (y1 - y0) / max(x1 - x0, 1e-9)))
    return 7.0 + 1.0 + (LEGEND_ROOM_IN if legend else 0.0), height + 1.3


def trajectories(log: RunLog) -> Figure:
    """Figure 5: every robot's path, a style each; the reverse phase drawn over it as a
    wide pale band of the robot's colour; circles at the starts, squares at the ends.
    """
    legend = len(log.traces) <= LEGEND_MAX
    fig = plt.figure(figsize=_map_size(_extent(log), legend), layout="constrained")
    draw_trajectories(fig, log, _titled(log))
    return fig


def draw_trajectories(fig: FigureBase, log: RunLog, title: Titled) -> None:
    """Figure 5 drawn into `fig` (a figure or a panel of one)."""
    legend = len(log.traces) <= LEGEND_MAX
    extent = _extent(log)
    ax = fig.subplots()
    draw_world(ax, log)
    if not legend:
        fleet_trajectories(ax, log)
    handles: list[Any] = []
    n = len(log.traces)
    for i, (rid, tr) in enumerate(log.traces.items() if legend else ()):
        style = _style(i)
        back = np.where(tr.direction < 0, tr.y_m, np.nan)
        ax.plot(tr.x_m, back, color=style["color"], lw=7, alpha=0.3, solid_capstyle="butt")
        # the first robots drawn wider, so that paths on top of each other all show
        lw = 1.2 + 0.9 * (n - 1 - i) if n <= len(LINESTYLES) else 1.2
        (line,) = ax.plot(tr.x_m, tr.y_m, lw=lw, label=rid, **style)
        handles.append(line)
        ax.plot(tr.x_m[0], tr.y_m[0], "o", color=style["color"], zorder=4)
        ax.plot(tr.x_m[-1], tr.y_m[-1], "s", color=style["color"], zorder=4)
    x0, x1, y0, y1 = extent
    ax.set(xlabel="x (m)", ylabel="y (m)", xlim=(x0, x1), ylim=(y0, y1))
    ax.set_aspect("equal", adjustable="box")
    ax.set_title(title("trajectories"))
    if legend:
        handles += [
            Patch(color="0.5", alpha=0.3, label="reverse (pale band)"),
            Line2D([], [], ls="", marker="o", color="k", label="circle: start"),
            Line2D([], [], ls="", marker="s", color="k", label="square: end"),
        ]
        _legend_outside(fig, handles)
    ax.grid(True, alpha=0.3)


def separations(log: RunLog) -> Figure:
    """Figure 6: l and phi of every follower against l_d and phi_d."""
    fleet = len(_followers(log)) > LEGEND_MAX
    width = 9 + (0 if fleet else LEGEND_ROOM_IN)
    fig = plt.figure(figsize=(width, 7), layout="constrained")
    draw_separations(fig, log, _titled(log))
    return fig


def draw_separations(fig: FigureBase, log: RunLog, title: Titled) -> None:
    """Figure 6 drawn into `fig` (a figure or a panel of one)."""
    followers = _followers(log)
    fleet = len(followers) > LEGEND_MAX
    ax_l, ax_p = fig.subplots(2, 1, sharex=True)
    handles: list[Any] = []
    lines_l, lines_p, desired_l, desired_p = [], [], [], []
    for i, rid in enumerate(followers):
        parents = [p for p in tracked_series(log, rid) if p]
        leader = max(set(parents), key=parents.count)  # the robot it tracked most
        series = error_series(log, rid)
        l_d, phi_d = log.formation.polar_of(rid, leader)
        style = _style(i + 1)
        colour = style["color"]
        if fleet:
            lines_l.append(decimated(log.t_s, series.l_m))
            lines_p.append(decimated(log.t_s, np.degrees(series.phi_rad)))
            desired_l.append(l_d)
            desired_p.append(math.degrees(phi_d))
            continue
        (line,) = ax_l.plot(log.t_s, series.l_m, label=f"{rid} to {leader}", **style)
        handles.append(line)
        ax_l.axhline(l_d, color=colour, ls=":", lw=1)
        ax_p.plot(log.t_s, np.degrees(series.phi_rad), **style)
        ax_p.axhline(math.degrees(phi_d), color=colour, ls=":", lw=1)
    if fleet:
        for ax, lines, desired in ((ax_l, lines_l, desired_l), (ax_p, lines_p, desired_p)):
            collection(ax, lines, offset=1, lw=0.8)
            ax.hlines(sorted(set(desired)), 0, 1, transform=ax.get_yaxis_transform(),
                      colors="k", linestyles=":", lw=1)  # fmt: skip
        fleet_note(ax_l, len(followers))
    for ax in (ax_l, ax_p):
        _shade(ax, log)
        ax.grid(True, alpha=0.3)
    if not fleet:
        _legend_outside(fig, handles + _key(log, ("desired", ":")))
    ax_l.set(ylabel="l (m)", title=title("separations (dotted = desired; grey = reverse)"))
    ax_p.set(ylabel="phi (deg)", xlabel="t (s)")


def velocities(log: RunLog) -> Figure:
    """Figure 7: translational and rotational velocities against the run's limits."""
    width = 9 + (0 if len(log.traces) > LEGEND_MAX else LEGEND_ROOM_IN)
    fig = plt.figure(figsize=(width, 7), layout="constrained")
    draw_velocities(fig, log, _titled(log))
    return fig


def draw_velocities(fig: FigureBase, log: RunLog, title: Titled) -> None:
    """Figure 7 drawn into `fig` (a figure or a panel of one)."""
    limits = KinematicLimits.from_params(log.robot, log.scenario.limits)
    fleet = len(log.traces) > LEGEND_MAX
    ax_v, ax_w = fig.subplots(2, 1, sharex=True)
    handles: list[Any] = []
    if fleet:
        traces = list(log.traces.values())
        collection(ax_v, [decimated(log.t_s, tr.v_mps) for tr in traces], lw=0.8)
        w_deg = [decimated(log.t_s, np.degrees(tr.omega_radps)) for tr in traces]
        collection(ax_w, w_deg, lw=0.8)
        fleet_note(ax_v, len(traces))
    for i, (rid, tr) in enumerate(log.traces.items() if not fleet else ()):
        style = _style(i)
        (line,) = ax_v.plot(log.t_s, tr.v_mps, label=rid, **style)
        handles.append(line)
        ax_w.plot(log.t_s, np.degrees(tr.omega_radps), **style)
    for ax, bound in ((ax_v, limits.v_max_mps), (ax_w, math.degrees(limits.omega_max_radps))):
        ax.axhline(bound, color="k", ls="--", lw=1)
        ax.axhline(-bound, color="k", ls="--", lw=1)
        _shade(ax, log)
        ax.grid(True, alpha=0.3)
    if not fleet:
        _legend_outside(fig, handles + _key(log, ("limits", "--")))
    ax_v.set(ylabel="v (m/s)", title=title("velocity profiles (dashed = limits)"))
    ax_w.set(ylabel="omega (deg/s)", xlabel="t (s)")


# Rows of figure 4b, top to bottom: the navigation layer over the formation layer.
STATE_ROWS = (
    State.LOW_BATTERY,
    State.STALLED,
    State.FAULT,
    State.ESTOPPED,
    State.STUCK,
    State.EMERGENCY_STOP,
    State.ARRIVED,
    State.DEADLOCK_TURN,
    State.DEADLOCK_REVERSE,
    State.RESHAPE,
    State.TELEOP,
    State.WANDER,
    State.NAVIGATE,
    State.AVOID,
    State.JOIN,
    State.HOLD,
    State.FORMATION_REVERSE,
    State.FORMATION_TRACK,
)


def _state_names(log: RunLog) -> list[str]:
    """The rows of figure 4b, bottom to top: the states the run went through."""
    seen = {s for tr in log.traces.values() for s in tr.states}
    names = [str(s) for s in reversed(STATE_ROWS) if s in seen]
    return names + sorted(seen - set(names))


def states(log: RunLog) -> Figure:
    """Figure 4b: each robot's behaviour state over time (navigation layer above the
    formation layer), and below it which robot led, epoch by epoch.
    """
    width = 10 + (0 if len(log.traces) > LEGEND_MAX else LEGEND_ROOM_IN)
    height = 1.6 + 0.45 * len(_state_names(log)) + 1.0
    fig = plt.figure(figsize=(width, height), layout="constrained")
    draw_states(fig, log, _titled(log))
    return fig


def draw_states(fig: FigureBase, log: RunLog, title: Titled) -> None:
    """Figure 4b drawn into `fig` (a figure or a panel of one)."""
    names = _state_names(log)
    index = {name: i for i, name in enumerate(names)}
    ax, ax_lead = fig.subplots(
        2, 1, sharex=True, gridspec_kw={"height_ratios": [max(2, len(names)), 1.5]}
    )
    fleet = len(log.traces) > LEGEND_MAX
    handles: list[Any] = []
    steps = []
    for i, (rid, tr) in enumerate(log.traces.items()):
        if fleet:  # a step line's corners, decimated; the robots spread within a row
            lift = np.array([index[s] for s in tr.states], dtype=float) + 0.6 * i / len(log.traces)
            t = np.asarray(log.t_s[: len(lift)])
            steps.append(decimated(np.repeat(t, 2)[1:], np.repeat(lift, 2)[:-1]))
            continue
        level = [index[s] + 0.08 * i for s in tr.states]
        (line,) = ax.step(log.t_s, level, where="post", label=rid, **_style(i))
        handles.append(line)
    if fleet:
        collection(ax, steps, lw=0.6)
        fleet_note(ax, len(log.traces))
    ax.set_yticks(range(len(names)), names)
    ax.set(title=title("behaviour states over time"))
    ax.grid(True, alpha=0.3)
    if not fleet:
        _legend_outside(fig, handles)
    _leadership_panel(ax_lead, log)


def _leadership_panel(ax: Axes, log: RunLog) -> None:
    leaders = leader_series(log)
    ids = list(log.formation.robot_ids)
    colour = {rid: COLOURS[i % len(COLOURS)] for i, rid in enumerate(ids)}
    start = 0
    for k in range(1, len(leaders) + 1):
        if k == len(leaders) or leaders[k] != leaders[start]:
            t0, t1 = float(log.t_s[start]), float(log.t_s[min(k, len(leaders) - 1)])
            ax.axvspan(t0, t1, color=colour[leaders[start]], alpha=0.35, lw=0)
            ax.text((t0 + t1) / 2, 0.5, leaders[start], ha="center", va="center", fontsize=8)
            start = k
    rows = [tr.epochs for tr in log.traces.values() if tr.epochs]
    epochs = np.max(np.array(rows), axis=0) if rows else np.zeros(len(log.t_s), dtype=int)
    for k in np.flatnonzero(np.diff(epochs) > 0).tolist():
        ax.axvline(float(log.t_s[k + 1]), color="k", lw=1)
        ax.text(float(log.t_s[k + 1]), 0.9, f" epoch {int(epochs[k + 1])}", fontsize=7, va="top")
    ax.set(yticks=[], xlabel="t (s)", ylabel="leader")


def deadend_escape(log: RunLog) -> Figure:
    """The dead-end escape: the way in, the deadlock reverse back out (dashed), the way
    round; and the errors of every follower while the group reverses, against the
    formation-core bounds (measured from `settle_s` after the switch, shaded before).
    A group that went round without reversing is drawn and said so.
    """
    fig, (ax_map, ax_err) = plt.subplots(1, 2, figsize=(15, 6), width_ratios=[1.3, 1])
    draw_world(ax_map, log)
    for i, (rid, tr) in enumerate(log.traces.items()):
        colour = COLOURS[i % len(COLOURS)]
        ax_map.plot(tr.x_m, tr.y_m, color=colour, lw=1.0, label=rid)
        back = np.where(tr.direction < 0, tr.y_m, np.nan)
        ax_map.plot(tr.x_m, back, color=colour, lw=2.5, ls="--")
        ax_map.plot(tr.x_m[0], tr.y_m[0], "o", color=colour)
    direction = leader_direction(log)
    reversing = direction < 0
    how = "in, back out in formation (dashed), round" if reversing.any() else "round, no reverse"
    ax_map.set(xlabel="x (m)", ylabel="y (m)", aspect="equal",
               title=f"{log.scenario.name}: {how}")  # fmt: skip
    ax_map.legend(loc="upper left")
    ax_map.grid(True, alpha=0.3)
    _, backward = phase_masks(log)
    for i, rid in enumerate(_followers(log)):
        series = error_series(log, rid)
        colour = COLOURS[(i + 1) % len(COLOURS)]
        ax_err.plot(log.t_s, np.where(reversing, series.linear_pct, np.nan), color=colour,
                    label=f"{rid} linear %")  # fmt: skip
        ax_err.plot(log.t_s, np.where(reversing, series.angular_pct, np.nan), color=colour,
                    ls="--", label=f"{rid} angular %")  # fmt: skip
        ax_err.plot(log.t_s, np.where(reversing, series.orientation_deg, np.nan), color=colour,
                    ls=":", label=f"{rid} orientation deg")  # fmt: skip
    spans = np.flatnonzero(reversing)
    label_t = float(log.t_s[spans[-1]]) if spans.size else float(log.t_s[0])
    for bound, text in (
        (0.5, "bound 0.5 (linear %, orientation deg)"),
        (0.3, "bound 0.3 (angular %)"),
    ):
        ax_err.axhline(bound, color="k", lw=0.8, ls="-.")
        ax_err.text(label_t, bound, text, fontsize=7, va="bottom", ha="right")
    settling = reversing & ~backward
    for k in np.flatnonzero(settling).tolist():
        ax_err.axvspan(float(log.t_s[k]), float(log.t_s[k]) + log.scenario.dt_s,
                       color="0.9", lw=0)  # fmt: skip
    if spans.size:
        ax_err.set_xlim(float(log.t_s[spans[0]]) - 2, float(log.t_s[spans[-1]]) + 2)
    else:
        ax_err.text(0.5, 0.5, "no reverse", transform=ax_err.transAxes, ha="center")
    ax_err.set_yscale("symlog", linthresh=0.01)
    ax_err.set(xlabel="t (s)", ylabel="error (% or deg)",
               title="errors while reversing (grey: first settle_s, not measured)")  # fmt: skip
    ax_err.grid(True, alpha=0.3)
    ax_err.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    return fig


# The paper's four by file name (their names, in this order, are `FIGURE_FILES`).
FIGURES: dict[str, Callable[[RunLog], Figure]] = dict(
    zip(FIGURE_FILES, (states, trajectories, separations, velocities), strict=True)
)
# The panels of the paper figure, in the paper's order: what each draws and its title.
PAPER_PANELS: tuple[tuple[str, Callable[[FigureBase, RunLog, Titled], None]], ...] = (
    ("(a) fig. 4b", draw_states),
    ("(b) fig. 5", draw_trajectories),
    ("(c) fig. 6", draw_separations),
    ("(d) fig. 7", draw_velocities),
)


def paper_figure(log: RunLog) -> Figure:
    """The paper's figures 4b, 5, 6 and 7 of one run as the four panels of one figure,
    (a) to (d), two by two, each panel's legend right of it; the scenario and the
    controller named once, above them all.
    """
    legend_in = 0.0 if len(log.traces) > LEGEND_MAX else LEGEND_ROOM_IN
    x0, x1, y0, y1 = _extent(log)
    map_in = 7.0 * min(1.6, max(0.45, (y1 - y0) / max(x1 - x0, 1e-9)))
    top_in = max(1.6 + 0.45 * len(_state_names(log)) + 1.0, map_in + 1.3)
    fig = plt.figure(figsize=(2 * (9.5 + legend_in), top_in + 7.5), layout="constrained")
    grid = fig.subfigures(2, 2, height_ratios=[top_in, 7.5], wspace=0.02, hspace=0.02)
    panels: list[FigureBase] = list(cast("npt.NDArray[Any]", grid).ravel())  # (2 x 2)
    for panel, (label, draw) in zip(panels, PAPER_PANELS, strict=True):
        draw(panel, log, _labelled(label))
    fig.suptitle(
        f"{log.scenario.name} / {log.scenario.controller.kind}", fontsize=14, fontweight="bold"
    )
    return fig


def _top(values: npt.NDArray[np.float64]) -> float:
    """The largest finite value (0 if none)."""
    finite = values[np.isfinite(values)]
    return float(finite.max()) if finite.size else 0.0


def _labelled(label: str) -> Titled:
    """A panel's titles: its label, then what it shows."""
    return lambda what: f"{label}: {what}"


def has_estimates(log: RunLog) -> bool:
    """Whether the robots of `log` ran the pose estimator and published its covariance."""
    if not log.scenario.localisation.estimator:
        return False
    return any(
        tr.cov.shape[0] == len(log.t_s) and bool(np.isfinite(tr.cov).all(axis=1).any())
        for tr in log.traces.values()
    )


def estimation(log: RunLog) -> Figure:
    """How well each robot knew its pose (a run with the pose estimator on): its published
    estimate against ground truth over time, the position and heading errors with the
    2-sigma bound of the covariance it published with them, and the NEES against its 95 %
    band (an honest filter keeps about 95 % of its steps inside).
    """
    legend = len(log.traces) <= LEGEND_MAX
    fig = plt.figure(figsize=(9 + (LEGEND_ROOM_IN if legend else 0), 8.5), layout="constrained")
    ax_p, ax_h, ax_n = fig.subplots(3, 1, sharex=True)
    handles: list[Any] = []
    settled = log.t_s >= log.scenario.initial_settle_s
    tops = {"position": [0.0], "heading": [0.0]}  # what the settled run reaches
    for i, (rid, tr) in enumerate(log.traces.items()):
        if tr.cov.shape[0] != len(log.t_s):
            continue
        style = _style(i) if legend else {"color": COLOURS[i % len(COLOURS)], "ls": "-"}
        position_m, heading_rad, errors = pose_errors(tr)
        sigma_xy_m = np.sqrt(np.maximum(tr.cov[:, 0] + tr.cov[:, 3], 0.0))
        sigma_h_deg = np.degrees(np.sqrt(np.maximum(tr.cov[:, 5], 0.0)))
        value = nees(errors, tr.cov)
        finite = value[settled & np.isfinite(value)]
        inside = float(np.mean((finite >= NEES_BAND[0]) & (finite <= NEES_BAND[1])))
        share = f" ({100 * inside:.0f} % in band)" if finite.size else ""
        lw = 0.8 if legend else 0.5
        (line,) = ax_p.plot(log.t_s, 1e3 * position_m, lw=lw, label=f"{rid}{share}", **style)
        handles.append(line)
        ax_p.plot(log.t_s, 2e3 * sigma_xy_m, color=style["color"], ls=":", lw=1.2)
        ax_h.plot(log.t_s, np.degrees(heading_rad), lw=lw, **style)
        ax_h.fill_between(log.t_s, -2 * sigma_h_deg, 2 * sigma_h_deg, color=style["color"],
                          alpha=0.12, lw=0)  # fmt: skip
        ax_n.plot(log.t_s, value, lw=0.5, alpha=0.8, **style)
        tops["position"] += [_top(1e3 * position_m[settled]), _top(2e3 * sigma_xy_m[settled])]
        tops["heading"] += [_top(np.degrees(np.abs(heading_rad[settled]))),
                            _top(2 * sigma_h_deg[settled])]  # fmt: skip
    # Fitted to the run after it settled: the start's covariance, tens of times
    # larger, would flatten everything after it.
    ax_p.set_ylim(0.0, 1.15 * max(tops["position"]) or 1.0)
    heading_deg = 1.15 * max(tops["heading"]) or 1.0
    ax_h.set_ylim(-heading_deg, heading_deg)
    ax_n.axhspan(*NEES_BAND, color="0.85", lw=0)
    ax_n.set_yscale("log")
    for ax in (ax_p, ax_h, ax_n):
        ax.axvline(log.scenario.initial_settle_s, color="k", lw=0.8, ls="-.")
        ax.grid(True, alpha=0.3)
    ax_p.set(ylabel="position error (mm)",
             title=_title(log, "pose estimate against ground truth"))  # fmt: skip
    ax_h.set(ylabel="heading error (deg)")
    ax_n.set(ylabel="NEES", xlabel="t (s)")
    if legend:
        keys = [
            Line2D([], [], color="k", ls=":", lw=1.2, label="2 sigma, position"),
            Patch(color="k", alpha=0.12, label="2 sigma, heading"),
            Patch(color="0.85", label="NEES 95 % band"),
            Line2D([], [], color="k", ls="-.", lw=0.8, label="settled: measured from here"),
        ]
        _legend_outside(fig, [*handles, *keys])
    return fig


def write_figures(
    log: RunLog,
    folder: Path,
    *,
    fmt: FigureFormat = "png",
    dpi: int = DEFAULT_DPI,
    paper: bool = False,
) -> list[Path]:
    """Draw every figure of `log` into `folder` as `fmt` files (`dpi`: the PNG's pixels
    per inch; PDF and SVG are vector): the paper's four (`FIGURES`), the estimation
    figure for a run with the pose estimator on, and with `paper` the four as one PDF
    (`PAPER_FIGURE`); returns the files written.
    """
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, draw in FIGURES.items():
        fig = draw(log)
        written.append(save_figure(fig, folder / figure_name(name, fmt), dpi=dpi))
    if has_estimates(log):
        path = folder / figure_name(ESTIMATION_FIGURE, fmt)
        written.append(save_figure(estimation(log), path, dpi=dpi))
    if paper:
        written.append(save_figure(paper_figure(log), folder / PAPER_FIGURE, dpi=dpi))
    return written


def save_figure(fig: Figure, path: Path, *, dpi: int = DEFAULT_DPI) -> Path:
    """Write `fig` at `path` (its format from the suffix: png, pdf or svg) and close it."""
    if not DPI_MIN <= dpi <= DPI_MAX:
        raise ValueError(f"dpi must be within {DPI_MIN}-{DPI_MAX}, not {dpi}")
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fig.savefig(path, dpi=dpi)
    finally:
        plt.close(fig)
    return path
