"""An explicit state machine: states, guarded transitions with priorities, entry/exit
actions and a log of every transition (the counterpart of the paper's Stateflow chart,
figure 4a; the log draws figure 4b).

The machine is generic over a context type `C` that guards read. Layers add states by
adding transitions; nothing here knows about robots.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Generic, TypeVar

from phalanx.core.states import TransitionEvent

C = TypeVar("C")

ANY_STATE = "*"


@dataclass(frozen=True)
class Transition(Generic[C]):
    """`source -> target` when `guard(ctx)` holds; higher `priority` is tried first.

    `source` may be `ANY_STATE` ("*"), which never fires into the state it is already in.
    `detail`, if given, adds the particulars of this firing to the logged reason.
    """

    source: str
    target: str
    guard: Callable[[C], bool]
    reason: str
    priority: int = 0
    detail: Callable[[C], str] | None = None

    def explain(self, ctx: C) -> str:
        """The reason logged when this transition fires with `ctx`."""
        if self.detail is None:
            return self.reason
        return f"{self.reason}: {self.detail(ctx)}"


@dataclass
class StateMachine(Generic[C]):
    """A flat state machine; call `update` once per control step.

    `absorbing` states are never left, not even by `ANY_STATE` transitions.
    """

    initial: str
    transitions: Sequence[Transition[C]]
    on_entry: Mapping[str, Callable[[C], None]] = field(default_factory=dict)
    on_exit: Mapping[str, Callable[[C], None]] = field(default_factory=dict)
    log: list[TransitionEvent] = field(default_factory=list)
    absorbing: frozenset[str] = frozenset()

    def __post_init__(self) -> None:
        self.state = self.initial
        self.entered_at_s = 0.0
        self._ordered = sorted(self.transitions, key=lambda tr: -tr.priority)
        self._from: dict[str, list[Transition[C]]] = {}

    @property
    def states(self) -> tuple[str, ...]:
        """Every state named by a transition, the initial one first."""
        names = [self.initial]
        for tr in self.transitions:
            names += [s for s in (tr.source, tr.target) if s != ANY_STATE and s not in names]
        return tuple(names)

    def _candidates(self) -> Iterable[Transition[C]]:
        if self.state in self.absorbing:
            return ()
        if self.state not in self._from:  # the same list every time: build it once
            self._from[self.state] = [
                tr
                for tr in self._ordered
                if tr.source == self.state or (tr.source == ANY_STATE and tr.target != self.state)
            ]
        return self._from[self.state]

    def update(self, ctx: C, t_s: float) -> TransitionEvent | None:
        """Take at most one transition (the highest-priority one whose guard holds)."""
        for tr in self._candidates():
            if tr.guard(ctx):
                return self._take(tr, ctx, t_s)
        return None

    def force(self, target: str, ctx: C, t_s: float, reason: str) -> TransitionEvent:
        """Move to `target` regardless of guards (used for external commands)."""
        return self._take(Transition(self.state, target, lambda _: True, reason), ctx, t_s)

    def _take(self, tr: Transition[C], ctx: C, t_s: float) -> TransitionEvent:
        if (exit_action := self.on_exit.get(self.state)) is not None:
            exit_action(ctx)
        event = TransitionEvent(t_s, self.state, tr.target, tr.explain(ctx))
        self.state, self.entered_at_s = tr.target, t_s
        self.log.append(event)
        if (entry_action := self.on_entry.get(tr.target)) is not None:
            entry_action(ctx)
        return event


def to_mermaid(machine: StateMachine[C], *, notes: Mapping[str, str] | None = None) -> str:
    """The machine as a Mermaid `stateDiagram-v2` (initial state, every transition with
    its priority and reason; `*` transitions drawn from an "any state" node).
    """
    lines = ["stateDiagram-v2", f"    [*] --> {machine.initial}"]
    if any(tr.source == ANY_STATE for tr in machine.transitions):
        lines.append('    state "any state" as ANY')
    for tr in sorted(machine.transitions, key=lambda t: (t.source, -t.priority, t.target)):
        source = "ANY" if tr.source == ANY_STATE else tr.source
        label = tr.reason.replace(":", " -").replace(";", ",")
        lines.append(f"    {source} --> {tr.target} : [{tr.priority}] {label}")
    for state in sorted(machine.absorbing):
        lines.append(f"    {state} --> [*]")
    for state, text in (notes or {}).items():
        lines.append(f"    note right of {state} : {text}")
    return "\n".join(lines) + "\n"
