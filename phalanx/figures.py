"""PNG figures of a run, the counterparts of the paper's figures 4b, 5, 6 and 7.

fig4b: behaviour state over time; fig5: trajectories with the reverse phase marked;
fig6: linear and angular separations against their desired values; fig7: velocity
profiles against the run's limits.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib as mpl

mpl.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from phalanx.agents.control.limits import KinematicLimits
from phalanx.metrics import error_series
from phalanx.simulator.batch import RunLog

COLOURS = ("tab:red", "tab:blue", "tab:green", "tab:purple", "tab:orange", "tab:brown")


def _followers(log: RunLog) -> list[str]:
    return [r for r in log.formation.robot_ids if log.formation.leader_of(r) is not None]


def _reverse_spans(log: RunLog) -> list[tuple[float, float]]:
    direction = log.traces[log.formation.root].direction
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


def _shade(ax: Axes, log: RunLog) -> None:
    for i, (a, b) in enumerate(_reverse_spans(log)):
        ax.axvspan(a, b, color="0.85", label="reverse" if i == 0 else None)


def trajectories(log: RunLog) -> Figure:
    """Figure 5: every robot's path; the reverse phase drawn thick and dashed."""
    fig, ax = plt.subplots(figsize=(8, 7))
    for i, (rid, tr) in enumerate(log.traces.items()):
        colour = COLOURS[i % len(COLOURS)]
        ax.plot(tr.x_m, tr.y_m, color=colour, lw=1.0, label=rid)
        back = np.where(tr.direction < 0, tr.y_m, np.nan)
        ax.plot(tr.x_m, back, color=colour, lw=2.5, ls="--")
        ax.plot(tr.x_m[0], tr.y_m[0], "o", color=colour)
        ax.plot(tr.x_m[-1], tr.y_m[-1], "s", color=colour)
    ax.set(xlabel="x (m)", ylabel="y (m)", aspect="equal")
    ax.set_title(
        f"{log.scenario.name} / {log.scenario.controller.kind}: trajectories "
        "(dashed = reverse; o start, s end)"
    )
    ax.legend()
    ax.grid(True, alpha=0.3)
    return fig


def separations(log: RunLog) -> Figure:
    """Figure 6: l and phi of every follower against l_d and phi_d."""
    fig, (ax_l, ax_p) = plt.subplots(2, 1, figsize=(9, 7), sharex=True)
    for i, rid in enumerate(_followers(log)):
        leader = log.formation.leader_of(rid)
        assert leader is not None  # noqa: S101
        series = error_series(log, rid)
        l_d, phi_d = log.formation.polar_of(rid, leader)
        colour = COLOURS[(i + 1) % len(COLOURS)]
        ax_l.plot(log.t_s, series.l_m, color=colour, label=f"{rid} to {leader}")
        ax_l.axhline(l_d, color=colour, ls=":", lw=1)
        ax_p.plot(log.t_s, np.degrees(series.phi_rad), color=colour, label=rid)
        ax_p.axhline(math.degrees(phi_d), color=colour, ls=":", lw=1)
    for ax in (ax_l, ax_p):
        _shade(ax, log)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper right")
    ax_l.set(ylabel="l (m)", title="separations (dotted = desired; grey = reverse)")
    ax_p.set(ylabel="phi (deg)", xlabel="t (s)")
    return fig


def velocities(log: RunLog) -> Figure:
    """Figure 7: translational and rotational velocities against the run's limits."""
    limits = KinematicLimits.from_params(log.robot, log.scenario.limits)
    fig, (ax_v, ax_w) = plt.subplots(2, 1, figsize=(9, 7), sharex=True)
    for i, (rid, tr) in enumerate(log.traces.items()):
        colour = COLOURS[i % len(COLOURS)]
        ax_v.plot(log.t_s, tr.v_mps, color=colour, label=rid)
        ax_w.plot(log.t_s, np.degrees(tr.omega_radps), color=colour, label=rid)
    for ax, bound in ((ax_v, limits.v_max_mps), (ax_w, math.degrees(limits.omega_max_radps))):
        ax.axhline(bound, color="k", ls="--", lw=1)
        ax.axhline(-bound, color="k", ls="--", lw=1)
        _shade(ax, log)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper right")
    ax_v.set(ylabel="v (m/s)", title="velocity profiles (dashed = limits)")
    ax_w.set(ylabel="omega (deg/s)", xlabel="t (s)")
    return fig


def states(log: RunLog) -> Figure:
    """Figure 4b: each robot's behaviour state over time."""
    names = sorted({s for tr in log.traces.values() for s in tr.states})
    index = {name: i for i, name in enumerate(names)}
    fig, ax = plt.subplots(figsize=(9, 1.2 + 0.6 * len(names)))
    for i, (rid, tr) in enumerate(log.traces.items()):
        level = [index[s] + 0.08 * i for s in tr.states]
        ax.step(log.t_s, level, where="post", color=COLOURS[i % len(COLOURS)], label=rid)
    ax.set_yticks(range(len(names)), names)
    ax.set(xlabel="t (s)", title="behaviour states over time")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper right")
    fig.tight_layout()
    return fig


FIGURES = {
    "fig4b_states.png": states,
    "fig5_trajectories.png": trajectories,
    "fig6_separations.png": separations,
    "fig7_velocities.png": velocities,
}


def write_figures(log: RunLog, folder: Path) -> list[Path]:
    """Draw every figure of `log` into `folder`; returns the files written."""
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, draw in FIGURES.items():
        fig = draw(log)
        path = folder / name
        fig.savefig(path, dpi=90)
        plt.close(fig)
        written.append(path)
    return written
