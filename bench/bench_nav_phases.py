"""Where a navigation step goes: a robot-step of a navigating run, phase by phase.

Runs navigating scenarios (`nav_field_wedge3`, `nav_field_collateral5`) and the paper's
scripted run (`paper_wedge`) in this process, stepped by `BatchRunner` the way
`phalanx run` steps them. Each scenario is run twice. The first run has no timers, and
gives the cost per robot-step. The second run has timers wrapped round the functions
each phase is made of. The wrapping happens from here, by patching the classes' methods
and the modules' names, so the brain itself is not changed.

A phase's time is its own: time spent in a nested timed phase counts for that phase
only. For example, the route planned inside steering counts as route planning, not as
steering. So the rows add up to the timed run's total. `PHASES` lists which functions
make up each phase. A function renamed or moved in the brain stops the benchmark with
its name, rather than letting its time slip into "the rest".

Every time is also given as a ratio to the calibration workload timed in the same run
(`bench/calibration.py`), in milli-cal per robot-step. The compiled kernels
(`phalanx.core.compiled`) are loaded before the first run; `PHALANX_KERNELS=numpy` times
numpy's code instead.

    .venv/bin/python bench/bench_nav_phases.py [--scenario nav_field_wedge3 ...] [--duration-s 240]
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from calibration import Calibration, load

from phalanx.agents.navigation import warm_kernels
from phalanx.agents.navigation.clearance import KERNELS
from phalanx.agents.perception import SonarGeometry
from phalanx.core.compiled import kernels
from phalanx.core.config_files import CONFIG_ROOT, apply_overrides, load_robot, load_scenario
from phalanx.runtime.batch import BatchRunner

NAVIGATION = ("nav_field_wedge3", "nav_field_collateral5")
SCRIPTED = "paper_wedge"

# Phase -> the functions it is made of: "module:Class.method" (patched on the class) or
# "module:function" (patched wherever a phalanx module holds that function by name).
PHASES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("world: sonar cast", ("phalanx.simulator.world:World.statuses",)),
    (
        "world: motion, odometry",
        ("phalanx.simulator.world:World.step", "phalanx.simulator.world:World.odometries"),
    ),
    ("sense: sonar read", ("phalanx.agents.perception:SonarGeometry.read_all",)),
    ("sense: masking the formation out", ("phalanx.agents.masking:mask_readings",)),
    ("sense: listen, leadership, estimate", ("phalanx.agents.agent:Agent.hear",)),
    ("sense: the rest of Senses.read", ("phalanx.agents.sensing:Senses.read",)),
    (
        "map update",
        (
            "phalanx.agents.navigation.fleet_map:FleetMap.add",
            "phalanx.agents.navigation.route:RoutePlanner.see",
            "phalanx.agents.navigation.grid:OccupancyMap.update",
            "phalanx.agents.navigation.grid:OccupancyMap.update_many",
        ),
    ),
    (
        "map: the fleet's own robots left out",
        ("phalanx.agents.navigation.fleet_map:FleetMap._obstacle_echoes",),
    ),
    (
        "route planning",
        (
            "phalanx.agents.navigation.route:RoutePlanner.towards",
            "phalanx.agents.navigation.route:RoutePlanner.way_exists",
        ),
    ),
    (
        "steering: candidate headings' clearance",
        (
            "phalanx.agents.shape:Shape.clearances",
            "phalanx.agents.navigation.steering:RecentEchoes.with_recent",
        ),
    ),
    ("steering: choosing the heading", ("phalanx.agents.navigation.steering:steer",)),
    (
        "steering: the rest",
        (
            "phalanx.agents.behaviours.leader:Steered.command",
            "phalanx.agents.behaviours.follower:Avoid.command",
        ),
    ),
    (
        "deadlock checks",
        (
            "phalanx.agents.leadership:group_deadlock",
            "phalanx.agents.sensing:Senses._dead_end",
            "phalanx.agents.sensing:Senses._stalled",
            "phalanx.agents.parts:Parts.retries_left",
        ),
    ),
    (
        "deadlock manoeuvres",
        (
            "phalanx.agents.behaviours.leader:DeadlockReverse.command",
            "phalanx.agents.behaviours.leader:DeadlockTurn.command",
        ),
    ),
    ("reshape weighing", ("phalanx.agents.parts:Parts.weigh_shapes",)),
    (
        "controller, spacing, limits",
        (
            "phalanx.agents.behaviours.follower:Track.command",
            "phalanx.agents.behaviours.leader:Scripted.command",
            "phalanx.agents.control.limits:CommandLimiter.apply",
            "phalanx.agents.control.spacing:Spacing.apply",
            "phalanx.agents.sensing:ContactGuard.apply",
        ),
    ),
    ("decide: the guards' context, the state machine", ("phalanx.agents.agent:Agent._decide",)),
    ("agent: the rest of Agent.step", ("phalanx.agents.agent:Agent.step",)),
    ("runner: recording the step", ("phalanx.runtime.batch:BatchRunner._record",)),
)
RUNNER_REST = "runner: the rest"


class Timers:
    """Each phase's own time (s): a call's time less that of the timed calls inside it."""

    def __init__(self) -> None:
        self.spent: Counter[str] = Counter()
        self._inner: list[float] = []  # the timed time inside each call under way

    def wrap(self, label: str, work: Callable[..., Any]) -> Callable[..., Any]:
        """`work`, its own time added to `spent[label]` on every call."""
        inner = self._inner

        def call(*args: Any, **kwargs: Any) -> Any:
            inner.append(0.0)
            started = time.perf_counter()
            try:
                return work(*args, **kwargs)
            finally:
                elapsed = time.perf_counter() - started
                self.spent[label] += elapsed - inner.pop()
                if inner:
                    inner[-1] += elapsed

        return call


def _resolve(target: str) -> tuple[Any, str, Any]:
    """(the object holding it, its name, the function) of "module:Class.method" or
    "module:function"; stops with the target's name if the brain has none such.
    """
    module_name, _, path = target.partition(":")
    try:
        owner: Any = importlib.import_module(module_name)
        *classes, name = path.split(".")
        for cls in classes:
            owner = getattr(owner, cls)
        return owner, name, owner.__dict__[name] if classes else getattr(owner, name)
    except (ImportError, AttributeError, KeyError) as exc:
        raise SystemExit(f"bench_nav_phases: no {target} any more ({exc}): update PHASES") from exc


def _holders(module: Any, name: str, function: Any) -> list[tuple[Any, str]]:
    """Every loaded phalanx module holding `function` as `name` (where it is looked up)."""
    held = [
        (m, name)
        for key, m in list(sys.modules.items())
        if key.startswith("phalanx.") and getattr(m, name, None) is function
    ]
    return held or [(module, name)]


@contextmanager
def timed_phases(timers: Timers) -> Iterator[None]:
    """Every function of `PHASES` wrapped in its phase's timer, put back afterwards."""
    patched: list[tuple[Any, str, Any]] = []
    try:
        for label, targets in PHASES:
            for target in targets:
                owner, name, function = _resolve(target)
                places = (
                    [(owner, name)] if isinstance(owner, type) else _holders(owner, name, function)
                )
                for place, attr in places:
                    patched.append((place, attr, function))
                    setattr(place, attr, timers.wrap(label, function))
        yield
    finally:
        for place, attr, function in reversed(patched):
            setattr(place, attr, function)


@dataclass(frozen=True)
class Measured:
    """One scenario: its robot-steps, the untimed run's wall time, the timed run's, and
    each phase's own time in the timed run (s).
    """

    name: str
    robot_steps: int
    untimed_s: float
    timed_s: float
    spent: dict[str, float]

    def per_step_s(self, seconds: float) -> float:
        """`seconds` per robot-step."""
        return seconds / self.robot_steps


def _runner(name: str, duration_s: float | None) -> BatchRunner:
    scenario = load_scenario(CONFIG_ROOT / "scenarios" / f"{name}.toml")
    if duration_s is not None:
        scenario = apply_overrides(scenario, [f"duration_s={duration_s}"])
    return BatchRunner(scenario)


def _run(runner: BatchRunner) -> float:
    started = time.perf_counter()
    runner.run()
    return time.perf_counter() - started


def measure(name: str, duration_s: float | None) -> Measured:
    """`name` run untimed, then timed phase by phase."""
    plain = _runner(name, duration_s)
    untimed = _run(plain)
    robot_steps = plain.done * len(plain.agents)
    runner, timers = _runner(name, duration_s), Timers()
    with timed_phases(timers):
        whole = _run(runner)
    spent = dict(timers.spent)
    spent[RUNNER_REST] = whole - sum(spent.values())
    return Measured(name, robot_steps, untimed, whole, spent)


def _cell(m: Measured, seconds: float, cal: Calibration) -> str:
    per = m.per_step_s(seconds)
    return (
        f"{1e6 * per:6.0f} µs {1e3 * cal.ratio(per):5.2f} mcal {100 * seconds / m.timed_s:3.0f} %"
    )


def print_table(results: list[Measured], cal: Calibration) -> None:
    """A row per phase, a column per scenario: µs and milli-cal per robot-step, share."""
    labels = [label for label, _ in PHASES] + [RUNNER_REST]
    width = max(len(label) for label in labels)
    print(f"\nper robot-step (µs, milli-cal, share of the timed run); load {load()}")
    print(f"{'phase':{width}s}  " + "  ".join(f"{m.name:>28s}" for m in results))
    for label in labels:
        print(
            f"{label:{width}s}  "
            + "  ".join(_cell(m, m.spent.get(label, 0.0), cal) for m in results)
        )
    print(f"{'timed run':{width}s}  " + "  ".join(_cell(m, m.timed_s, cal) for m in results))
    print(f"{'untimed run':{width}s}  " + "  ".join(_cell(m, m.untimed_s, cal) for m in results))


def print_costs(results: list[Measured], scripted: Measured | None, cal: Calibration) -> None:
    """Each run's cost per robot-step untimed, and against the scripted run's."""
    print("\ncost per robot-step, untimed run")
    for m in results:
        per = m.per_step_s(m.untimed_s)
        against = ""
        if scripted is not None and m is not scripted:
            against = f", {per / scripted.per_step_s(scripted.untimed_s):.1f}x {scripted.name}"
        print(
            f"  {m.name:24s} {1e3 * per:6.3f} ms ({1e3 * cal.ratio(per):5.2f} mcal), "
            f"{m.robot_steps} robot-steps in {m.untimed_s:5.2f} s{against}"
        )


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scenario", nargs="+", default=list(NAVIGATION))
    parser.add_argument("--scripted", default=SCRIPTED, help="the scripted run to compare with")
    parser.add_argument("--duration-s", type=float, default=None, help="(default: the scenario's)")
    args = parser.parse_args()
    warm_kernels(SonarGeometry.from_params(load_robot("p3dx")))  # (loaded before timing)
    print(f"kernels: {'numba' if kernels(KERNELS) is not None else 'numpy'}")
    cal = Calibration.measure()
    results = [measure(name, args.duration_s) for name in args.scenario]
    scripted = measure(args.scripted, None) if args.scripted else None
    shown = [*results, scripted] if scripted is not None else results
    print_table(shown, cal)
    print_costs(shown, scripted, cal)
    Calibration.measure()


if __name__ == "__main__":
    main()
