"""The state machine picture (`phalanx fsm`, docs/figures/fsm.*): every state once, in its
group's box; every transition an edge labelled with its guard; the same transitions as the
arbitration table in docs/BEHAVIOUR.md; and the committed figures are the ones the code draws.

The DOT source is read back by the renderer itself (`-Tjson`), so these tests check what
Graphviz understood, not what a regular expression finds in the text.
"""

from __future__ import annotations

import json
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from phalanx.agents.behaviours.stack import ARBITRATION, behaviour_machine, behaviour_transitions
from phalanx.agents.fsm import ANY_STATE, Transition
from phalanx.analysis.fsm_picture import (
    ANY_NODE,
    PictureError,
    cluster_id,
    guard_label,
    junction_branches,
    junction_id,
    picture_edges,
    render,
    renderer,
    to_dot,
)
from phalanx.cli import app
from phalanx.core.states import (
    FOLLOWER_STATES,
    LEADER_STATES,
    PAPER_STATES,
    ROBOT_STATES,
    STATE_GROUPS,
    State,
    StateGroup,
)

REPO = Path(__file__).resolve().parents[2]
FIGURES = REPO / "docs" / "figures"


def _renderer() -> list[str]:
    try:
        return renderer()
    except PictureError as exc:  # graphviz-pure is a dependency: only a broken install
        pytest.skip(f"no Graphviz renderer could be found ({exc})")


def _graph() -> dict[str, Any]:
    """The picture's DOT source as the renderer parsed it."""
    parsed: dict[str, Any] = json.loads(
        render(to_dot(behaviour_machine()), "json", command=_renderer())
    )
    return parsed


def _flat(label: str) -> str:
    return " ".join(label.replace("\\n", " ").split())


def test_every_state_is_in_exactly_one_group() -> None:
    assert set(STATE_GROUPS) == set(State)
    assert {s for s, g in STATE_GROUPS.items() if g == StateGroup.DRIVING} == LEADER_STATES
    assert {s for s, g in STATE_GROUPS.items() if g == StateGroup.FORMATION} == FOLLOWER_STATES
    assert {s for s, g in STATE_GROUPS.items() if g == StateGroup.ROBOT} == ROBOT_STATES
    assert {State.FORMATION_TRACK, State.FORMATION_REVERSE} <= PAPER_STATES


def test_every_state_is_drawn_once_inside_its_groups_box() -> None:
    graph = _graph()
    objects = graph["objects"]
    names = Counter(o["name"] for o in objects)
    for state in State:
        assert names[state.value] == 1, state
    boxes = {o["name"]: o for o in objects if o["name"].startswith("cluster_")}
    assert set(boxes) == {cluster_id(g) for g in StateGroup}
    for state, group in STATE_GROUPS.items():
        box = boxes[cluster_id(group)]
        assert box["label"] == group.value
        inside = {objects[i]["name"] for i in box["nodes"]}
        assert state.value in inside, (state, group)
        others = [b for n, b in boxes.items() if n != cluster_id(group)]
        assert all(state.value not in {objects[i]["name"] for i in b["nodes"]} for b in others)


def _drawn(graph: dict[str, Any]) -> list[tuple[str, str, str]]:
    """(tail, head, label) of every edge; a tail is the box it leaves from if it has one."""
    objects = graph["objects"]
    edges = []
    for edge in graph["edges"]:
        tail = edge.get("ltail") or objects[edge["tail"]]["name"]
        edges.append((tail, objects[edge["head"]]["name"], _flat(edge.get("label", ""))))
    return edges


def _tails(source: str) -> set[str]:
    """Where an edge standing for a transition from `source` may leave from."""
    if source == ANY_STATE:
        return {ANY_NODE}
    return {source, cluster_id(STATE_GROUPS[State(source)])}


def _drawn_by(tr: Transition[Any], edges: list[tuple[str, str, str]]) -> bool:
    tails = _tails(tr.source)
    group = STATE_GROUPS[State(tr.target)]
    branches = junction_branches(behaviour_transitions()).get(group, frozenset())
    heads = {tr.target} | ({junction_id(group)} if tr.target in branches else set())
    return any(t in tails and h in heads and lab == guard_label(tr) for t, h, lab in edges)


def test_every_transition_is_an_edge_labelled_with_its_guard() -> None:
    edges = _drawn(_graph())
    transitions = behaviour_transitions()
    missing = [(t.source, t.target, t.reason) for t in transitions if not _drawn_by(t, edges)]
    assert missing == []
    # A junction goes on to the states its folded transitions lead to, and nowhere else.
    for group, targets in junction_branches(transitions).items():
        assert {h for t, h, _ in edges if t == junction_id(group)} == targets
    # Labels are guards in words, never the bare priority the old picture showed.
    labels = [lab for t, _, lab in edges if t not in {"initial"} and not t.endswith("_junction")]
    assert all(lab and not lab.replace("/", "").isdigit() for lab in labels)


def _sources(tail: str) -> set[str]:
    """The states an edge leaving `tail` stands for."""
    if tail == ANY_NODE:
        return {ANY_STATE}
    groups = [g for g in StateGroup if cluster_id(g) == tail]
    return {s.value for s, g in STATE_GROUPS.items() if g in groups} or {tail}


def test_every_edge_stands_for_transitions_that_exist() -> None:
    transitions = behaviour_transitions()
    exists = {(t.source, t.target, guard_label(t)) for t in transitions}
    branches = {junction_id(g): t for g, t in junction_branches(transitions).items()}
    for tail, head, label in _drawn(_graph()):
        if tail == "initial" or tail in branches:
            continue
        for source in _sources(tail):
            for target in branches.get(head, {head}):
                assert (source, target, label) in exists, (tail, source, target, label)


def test_each_transition_is_drawn_by_exactly_one_edge() -> None:
    transitions = behaviour_transitions()
    drawn = Counter(id(tr) for e in picture_edges(transitions) for tr in e.transitions)
    assert sorted(drawn.values()) == [1] * len(transitions)
    assert len(picture_edges(transitions)) < len(transitions) / 1.5  # families folded


def test_the_picture_and_the_readme_table_come_from_the_same_transitions() -> None:
    edges = _drawn(_graph())
    entered = {h for _, h, _ in edges}
    for rule in ARBITRATION:
        for state in rule.behaviour.split(" / "):
            assert state in entered, (rule.priority, state)
    readme = (REPO / "docs" / "BEHAVIOUR.md").read_text()
    assert "](figures/fsm.svg)" in readme


def test_it_renders_to_svg_and_png() -> None:
    command = _renderer()
    source = to_dot(behaviour_machine())
    svg = ET.fromstring(render(source, "svg", command=command))  # noqa: S314 - our own output
    ns = "{http://www.w3.org/2000/svg}"
    titles = [t.text for t in svg.iter(f"{ns}title")]
    for state in State:
        assert titles.count(state.value) == 1, state
    assert render(source, "png", command=command)[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_committed_figures_are_the_ones_the_transitions_draw() -> None:
    command = _renderer()
    if Path(command[0]).name != "graphviz-pure":
        pytest.skip("only graphviz-pure draws the same bytes on every machine")
    source = to_dot(behaviour_machine())
    assert (FIGURES / "fsm.svg").read_bytes() == render(source, "svg", command=command)
    assert (FIGURES / "fsm.png").read_bytes() == render(source, "png", command=command)


def test_fsm_writes_png_svg_and_dot(tmp_path: Path) -> None:
    out = {ext: tmp_path / f"chart.{ext}" for ext in ("png", "svg", "dot")}
    args = ["fsm", "--png", str(out["png"]), "--svg", str(out["svg"]), "--dot", str(out["dot"])]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert out["png"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert ET.parse(out["svg"]).getroot().tag.endswith("svg")  # noqa: S314 - our own output
    assert out["dot"].read_text() == to_dot(behaviour_machine())


@pytest.mark.timeout(180)  # its child processes' own bound, and set-up
def test_fsm_into_a_missing_folder_says_so_without_a_traceback(tmp_path: Path) -> None:
    target = tmp_path / "nowhere" / "chart.svg"
    proc = subprocess.run(
        [sys.executable, "-m", "phalanx", "fsm", "--png", str(tmp_path / "a.png"),
         "--svg", str(target)],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert proc.returncode != 0
    assert f"cannot write {target}" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_a_renderer_failure_is_an_error_naming_it() -> None:
    command = _renderer()
    with pytest.raises(PictureError, match="failed"):
        render("digraph { a -> ", "svg", command=command)
