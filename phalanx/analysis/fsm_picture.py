"""Figure 4a as a person reads it: the behaviour state machine laid out by Graphviz's
`dot`, one box per group of states (`phalanx.core.states.STATE_GROUPS`) as a Stateflow
chart nests superstates, every edge labelled with its guard.

The picture is drawn from the same transitions the robots run and docs/BEHAVIOUR.md's
arbitration table is generated from (`behaviour_transitions()`). To stay readable, a
family of transitions is drawn as one edge where Stateflow would draw one:

- from every state of a group with one guard to one place: an edge from the group's box;
- from one state with one guard to several states of a group (the leader state the plan
  calls for): an edge to the group's connective junction (a small dot), which branches
  to those states.

The renderer is the `graphviz-pure` program (a self-contained port of `dot` installed
from PyPI with phalanx), or a system Graphviz's `dot` where that is missing.
"""

from __future__ import annotations

import html
import shutil
import subprocess
import sysconfig
import textwrap
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from phalanx.agents.fsm import ANY_STATE, StateMachine, Transition
from phalanx.core.errors import PhalanxError
from phalanx.core.states import PAPER_STATES, STATE_GROUPS, State, StateGroup, states_of

Format = Literal["png", "svg", "json"]  # json: the graph as Graphviz parsed and laid it out

# Tried in this order: the PyPI port first, so a picture is the same bytes everywhere.
RENDERERS = ("graphviz-pure", "dot")
RENDER_TIMEOUT_S = 60.0
LABEL_WIDTH = 26  # characters per line of an edge label
ANY_NODE = "ANY"

GROUP_COLOURS: dict[StateGroup, str] = {
    StateGroup.DRIVING: "#dbe8f6",
    StateGroup.FORMATION: "#dcefd9",
    StateGroup.SAFETY: "#f6ecd2",
    StateGroup.ROBOT: "#f6d9d5",
}
PAPER_FILL = "#fff6b3"
TITLE = "Behaviour state machine of one robot"
# What a group's junction picks by (the transitions into several leader states at once are
# `transitions._leader_targets`: the state the leader's plan calls for).
JUNCTION_NOTES = {StateGroup.DRIVING: "whichever the leader's plan calls for"}


class PictureError(PhalanxError):
    """No Graphviz renderer, it failed to draw the picture, or the file cannot be written."""


def guard_label(tr: Transition[Any]) -> str:
    """The short label of a transition's guard: its reason up to the first colon (what
    holds), without what follows (what the robot then does).
    """
    return tr.reason.split(":", 1)[0].strip()


@dataclass(frozen=True)
class Edge:
    """One arrow of the picture: from a state, a group's box (`cluster_id`) or any state
    (`ANY_STATE`) to a state or a group's junction (`junction_id`), labelled with the
    guard of the transitions it stands for.
    """

    tail: str
    head: str
    label: str
    transitions: tuple[Transition[Any], ...]


def cluster_id(group: StateGroup) -> str:
    """The DOT name of `group`'s box."""
    return "cluster_" + group.name.lower()


def junction_id(group: StateGroup) -> str:
    """The DOT name of `group`'s connective junction."""
    return group.name.lower() + "_junction"


_ORDER = {s.value: i for i, s in enumerate(State)}


def _in_order(states: Iterable[str]) -> list[str]:
    """`states` in the order `State` declares them (unknown names last)."""
    return sorted(states, key=lambda s: _ORDER.get(s, len(_ORDER)))


def _group(state: str) -> StateGroup | None:
    try:
        return STATE_GROUPS[State(state)]
    except ValueError:  # ANY_STATE, or a state no group has
        return None


Family = dict[tuple[str, str, StateGroup | None], list[Transition[Any]]]


def _fan_outs(transitions: Sequence[Transition[Any]]) -> Family:
    """Transitions by source, guard label and the group of their target."""
    families: Family = {}
    for tr in transitions:
        families.setdefault((tr.source, guard_label(tr), _group(tr.target)), []).append(tr)
    return families


def _fold_targets(transitions: Sequence[Transition[Any]]) -> list[Edge]:
    """Transitions from one state with one guard into several states of one group become
    one edge to that group's junction, where the junction branches to every one of them.
    """
    families = _fan_outs(transitions)
    branches = _junction_branches(families.values())
    edges = []
    for (source, label, group), family in families.items():
        targets = frozenset(tr.target for tr in family)
        if group is not None and len(targets) > 1 and targets == branches.get(group):
            edges.append(Edge(source, junction_id(group), label, tuple(family)))
        else:
            edges += [Edge(source, tr.target, label, (tr,)) for tr in family]
    return edges


def _junction_branches(
    families: Iterable[list[Transition[Any]]],
) -> dict[StateGroup, frozenset[str]]:
    """Per group, the widest set of its states one family of transitions fans out to."""
    widest: dict[StateGroup, frozenset[str]] = {}
    for family in families:
        targets = frozenset(tr.target for tr in family)
        group = _group(family[0].target)
        if group is not None and len(targets) > len(widest.get(group, ())):
            widest[group] = targets
    return {g: t for g, t in widest.items() if len(t) > 1}


def _fold_sources(edges: Sequence[Edge]) -> list[Edge]:
    """Edges with one guard to one place from every state of a group become one edge
    from the group's box.
    """
    families: dict[tuple[str, str], list[Edge]] = {}
    for edge in edges:
        families.setdefault((edge.head, edge.label), []).append(edge)
    folded = []
    for (head, label), family in families.items():
        group = _group(family[0].tail)
        tails = {e.tail for e in family}
        if group is not None and len(tails) > 1 and tails == set(states_of(group)):
            merged = tuple(tr for e in family for tr in e.transitions)
            folded.append(Edge(cluster_id(group), head, label, merged))
        else:
            folded += family
    return folded


def picture_edges(transitions: Sequence[Transition[Any]]) -> list[Edge]:
    """The arrows of the picture: every transition drawn by exactly one of them."""
    return _fold_sources(_fold_targets(transitions))


def junction_branches(transitions: Sequence[Transition[Any]]) -> dict[StateGroup, frozenset[str]]:
    """Per group with a junction, the states its junction branches to."""
    return _junction_branches(_fan_outs(transitions).values())


def _quote(text: str) -> str:
    escaped = text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
    return f'"{escaped}"'


def _attrs(**attrs: str | float) -> str:
    return "[" + ", ".join(f"{k}={_quote(str(v))}" for k, v in attrs.items()) + "]"


def _state_node(state: str, *, absorbing: bool) -> str:
    paper = state in PAPER_STATES
    attrs: dict[str, str | float] = {
        "label": state,
        "fillcolor": PAPER_FILL if paper else "white",
        "penwidth": 2.4 if paper else 1.0,
    }
    if absorbing:
        attrs["peripheries"] = 2
    return f"    {state} {_attrs(**attrs)};"


def _cluster(group: StateGroup, machine: StateMachine[Any], junction: bool) -> list[str]:
    states = _in_order(states_of(group))
    lines = [
        f"  subgraph {cluster_id(group)} {{",
        f"    graph {_attrs(label=group.value, fillcolor=GROUP_COLOURS[group])};",
    ]
    lines += [_state_node(s, absorbing=s in machine.absorbing) for s in states]
    if junction:
        lines.append(
            f"    {junction_id(group)} "
            f"{_attrs(shape='circle', style='filled', fillcolor='black', label='', width=0.14)};"
        )
    return [*lines, "  }"]


def _edge_line(edge: Edge, representative: Mapping[str, str], side: str | None) -> str:
    label = textwrap.fill(edge.label, LABEL_WIDTH, break_on_hyphens=False)
    attrs: dict[str, str | float] = {"label": label}
    if side is not None:
        attrs |= {"tailport": side, "headport": side}
    tail = representative.get(edge.tail, edge.tail)
    if tail != edge.tail:
        attrs["ltail"] = edge.tail
    if edge.tail == ANY_STATE:
        tail = ANY_NODE
    return f"  {tail} -> {edge.head} {_attrs(**attrs)};"


GRAPH_ATTRS = (
    '  graph [rankdir="TB", compound="true", newrank="true", nodesep="0.45", ranksep="1.0", '
    'fontname="Helvetica", fontsize="15", labelloc="t", style="rounded,filled", '
    'pencolor="#8a8a8a"];',
    '  node [shape="box", style="rounded,filled", fontname="Helvetica", fontsize="12", '
    'margin="0.12,0.06"];',
    '  edge [fontname="Helvetica", fontsize="9", color="#555555", arrowsize="0.7"];',
)


def _sides(edges: Sequence[Edge]) -> dict[tuple[str, str], str]:
    """Two states with an edge each way: one of the two leaves and enters on the west
    sides (drawn along one path, their labels would land on each other).
    """
    pairs = {(e.tail, e.head) for e in edges}
    return {
        (a, b): "w"
        for a, b in pairs
        if (b, a) in pairs and a in _ORDER and b in _ORDER and _ORDER[a] < _ORDER[b]
    }


def _graph_label(title: str, branches: dict[StateGroup, frozenset[str]]) -> str:
    """The title in bold over the key, as a Graphviz HTML-like label."""
    key = [
        "yellow, bold: the states of the paper's chart",
        "an arrow from a box: from every state in it",
        "double border: never left",
    ]
    for group, targets in branches.items():
        choices = ", ".join(_in_order(targets))
        how = JUNCTION_NOTES.get(group, "as the guards pick")
        key.insert(2, f"black dot in {group.value}: on to {choices}, {how}")
    body = html.escape("; ".join(key), quote=False)
    return f'<<b>{html.escape(title, quote=False)}</b><br/><font point-size="12">{body}</font>>'


def to_dot(machine: StateMachine[Any], *, title: str = TITLE) -> str:
    """The machine as Graphviz DOT source: a box per group holding its states, the
    paper's states highlighted, the initial state marked, every transition an edge.
    """
    edges = picture_edges(machine.transitions)
    branches = junction_branches(machine.transitions)
    lines = ["digraph behaviour {", *GRAPH_ATTRS, f"  label={_graph_label(title, branches)};"]
    for group in StateGroup:
        lines += _cluster(group, machine, junction=group in branches)
    lines += _entry_lines(machine, any_state=any(e.tail == ANY_STATE for e in edges))
    for group, targets in branches.items():
        lines += [f"  {junction_id(group)} -> {t};" for t in _in_order(targets)]
    representative = {cluster_id(g): _in_order(states_of(g))[0] for g in StateGroup}
    sides = _sides(edges)
    lines += [_edge_line(e, representative, sides.get((e.tail, e.head))) for e in edges]
    return "\n".join([*lines, "}"]) + "\n"


def _entry_lines(machine: StateMachine[Any], *, any_state: bool) -> list[str]:
    lines = [
        f"  initial {_attrs(shape='point', width=0.12, label='')};",
        f"  initial -> {machine.initial} {_attrs(style='dashed', label='default')};",
    ]
    if any_state:
        lines.append(
            f"  {ANY_NODE} {_attrs(label='any state', shape='box', style='dashed,rounded')};"
        )
    return lines


def renderer() -> list[str]:
    """The command that renders DOT: `graphviz-pure` beside this Python (its scripts
    folder) or on the PATH, else `dot` on the PATH.
    """
    scripts = sysconfig.get_path("scripts")
    for name in RENDERERS:
        found = shutil.which(name, path=scripts) or shutil.which(name)
        if found is not None:
            return [found]
    raise PictureError(
        "no Graphviz renderer found: install one with `pip install 'phalanx[fsm]'` "
        "(or a system Graphviz, which provides `dot`)"
    )


def render(dot: str, fmt: Format, *, command: Sequence[str] | None = None) -> bytes:
    """`dot` drawn as `fmt` (PNG or SVG bytes, or the laid-out graph as JSON)."""
    argv = [*(command or renderer()), "-Kdot", f"-T{fmt}"]
    try:
        proc = subprocess.run(  # noqa: S603 - argv is the renderer found above and fixed flags
            argv, input=dot.encode(), capture_output=True, timeout=RENDER_TIMEOUT_S, check=False
        )
    except subprocess.TimeoutExpired as exc:
        raise PictureError(f"{argv[0]} took over {RENDER_TIMEOUT_S:.0f} s") from exc
    if proc.returncode != 0 or not proc.stdout:
        message = proc.stderr.decode(errors="replace").strip()[-2000:]
        raise PictureError(f"{argv[0]} failed (exit {proc.returncode}): {message}")
    return proc.stdout


def save_fsm_picture(
    machine: StateMachine[Any],
    *,
    png: Path | None = None,
    svg: Path | None = None,
    dot: Path | None = None,
) -> list[Path]:
    """Draw `machine` into a PNG and/or an SVG file, and write its DOT source to `dot`;
    the paths written.
    """
    source = to_dot(machine)
    outputs: list[tuple[Path | None, Callable[[], bytes]]] = [
        (dot, source.encode),
        (png, lambda: render(source, "png")),
        (svg, lambda: render(source, "svg")),
    ]
    written = []
    for path, content in outputs:
        if path is not None:
            _write(path, content())
            written.append(path)
    return written


def _write(path: Path, content: bytes) -> None:
    try:
        path.write_bytes(content)
    except OSError as exc:
        raise PictureError(f"cannot write {path}: {exc.strerror or exc}") from exc
