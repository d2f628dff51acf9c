"""The architecture's rules as tests: the import contract between layers, the CLI a leaf
that builds nothing the runtime assembles, agents started from a spec and never from a
command line built by hand, no loop of imports between modules, a repository that stands
on its own, and the arbitration table in docs/BEHAVIOUR.md equal to the one the
transitions generate.
"""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from phalanx.agents.behaviours.stack import arbitration_markdown
from phalanx.drivers import BACKENDS

REPO = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
PACKAGE_DIRS = ("phalanx", "agents", "drivers", "simulator")
MAX_STEP_LINES = 40
CLI_DIR = REPO / "phalanx" / "cli"
# What the runtime's factory (`phalanx.runtime.agent_process.run_agent`) puts together
# into a running agent, and nothing else does: the CLI parses its options into a spec and
# hands it over (`phalanx.runtime.process_spec`), importing none of these, not even as
# types. (Driver backends too: the registry opens one from a spec's driver choice.)
ASSEMBLED_MODULES = frozenset(
    {
        "phalanx.drivers.base",
        "phalanx.drivers.safety",
        "phalanx.runtime.agent",
        "phalanx.runtime.clock",
        "phalanx.runtime.positioning",
        "phalanx.runtime.robot_io",
        "phalanx.telemetry.stream",
        *(entry.module for entry in BACKENDS.values()),
    }
)
ASSEMBLED_NAMES = frozenset(
    {
        "AgentRuntime",
        "Driver",
        "DriverIO",
        "EpochClock",
        "PositioningInbox",
        "RuntimeOptions",
        "SafeDriver",
        "Telemetry",
        "WorldLink",
        "open_camera",
        "open_driver",
    }
)


def _lint_imports(
    root: Path, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    tool = BIN / "lint-imports"
    if not tool.exists():
        pytest.skip("import-linter is not installed in this environment (install '.[dev]')")
    return subprocess.run(
        [str(tool), "--config", str(REPO / "pyproject.toml")],
        cwd=root, capture_output=True, text=True, timeout=300, check=False, env=env,
    )  # fmt: skip


def test_every_layer_imports_only_its_own_and_those_below() -> None:
    proc = _lint_imports(REPO)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert "0 broken" in proc.stdout


@pytest.mark.slow
def test_the_contract_fails_on_an_upward_import(tmp_path: Path) -> None:
    # A copy of the package in which the bottom layer imports the CLI: the same contract
    # must call it broken, naming the import.
    copy = tmp_path / "src"
    copy.mkdir()
    for name in PACKAGE_DIRS:
        shutil.copytree(REPO / name, copy / name, symlinks=True)
    geometry = copy / "phalanx" / "core" / "geometry.py"
    geometry.write_text(geometry.read_text() + "\nimport phalanx.cli  # noqa: E402\n")
    env = {**os.environ, "PYTHONPATH": str(copy)}
    probe = subprocess.run(
        [sys.executable, "-c", "import phalanx, sys; sys.stdout.write(phalanx.__file__)"],
        cwd=copy, capture_output=True, text=True, timeout=60, check=False, env=env,
    )  # fmt: skip
    if not probe.stdout.startswith(str(copy)):
        pytest.skip(f"the copy is not what imports as phalanx here ({probe.stdout!r})")
    proc = _lint_imports(copy, env)
    assert proc.returncode != 0
    assert "phalanx.core.geometry -> phalanx.cli" in proc.stdout


def _python_files() -> list[Path]:
    return sorted(p for d in PACKAGE_DIRS for p in (REPO / d).rglob("*.py") if p.is_file())


def _classes(path: Path) -> list[ast.ClassDef]:
    return [n for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.ClassDef)]


def _module_name(path: Path, root: Path = REPO) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[0] != "phalanx":
        parts.insert(0, "phalanx")  # agents/, drivers/, simulator/ are phalanx's subpackages
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported(node: ast.Import | ast.ImportFrom, package: list[str]) -> list[tuple[str, str]]:
    """What one import statement names: (module, name taken from it, "" for none), a
    relative module resolved against `package`.
    """
    if isinstance(node, ast.Import):
        return [(a.name, "") for a in node.names]
    base = node.module or ""
    if node.level:
        base = ".".join([*package[: len(package) - node.level + 1], *([base] if base else [])])
    return [(base, a.name) for a in node.names]


def _all_imports(path: Path, root: Path = REPO) -> list[tuple[int, str, str]]:
    """Every import in `path` (a file of the package in `root`) wherever it stands (the
    top level, inside functions, under `if TYPE_CHECKING`): (line, module, name taken
    from it or "").
    """
    name = _module_name(path, root)
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    return [
        (node.lineno, module, taken)
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Import | ast.ImportFrom)
        for module, taken in _imported(node, package)
    ]


def _imports_at_load(path: Path, name: str, modules: set[str]) -> set[str]:
    """The package's modules `path` imports when it loads: its top level, not the lazy
    imports inside functions nor those under `if TYPE_CHECKING`."""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    found: set[str] = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            continue
        for n in ast.walk(node):
            if isinstance(n, ast.Import | ast.ImportFrom):
                for module, taken in _imported(n, package):
                    found.update([module, f"{module}.{taken}"] if taken else [module])
    return (found & modules) - {name}


def _in_cli(path: Path) -> bool:
    return path.is_relative_to(CLI_DIR)


def _names_the_cli(module: str, taken: str) -> bool:
    named = [module, f"{module}.{taken}"] if taken else [module]
    return any(n == "phalanx.cli" or n.startswith("phalanx.cli.") for n in named)


def test_nothing_but_the_entry_point_imports_the_cli() -> None:
    # The layers contract says so for the layers' modules; this says it for every module
    # and every import, lazy or for types only.
    hits = [
        f"{_module_name(path)}:{line} imports {module}{'.' + taken if taken else ''}"
        for path in _python_files()
        if not _in_cli(path) and _module_name(path) != "phalanx.__main__"
        for line, module, taken in _all_imports(path)
        if _names_the_cli(module, taken)
    ]
    assert hits == []


def cli_builds(paths: list[Path], root: Path = REPO) -> list[str]:
    """Where modules of the CLI (`paths`, in the package in `root`) import what the
    runtime's factory assembles.
    """
    return [
        f"{_module_name(path, root)}:{line} imports {module}{'.' + taken if taken else ''}"
        for path in paths
        for line, module, taken in _all_imports(path, root)
        if module in ASSEMBLED_MODULES
        or f"{module}.{taken}" in ASSEMBLED_MODULES
        or taken in ASSEMBLED_NAMES
    ]


def test_the_cli_builds_no_part_of_an_agent() -> None:
    paths = sorted(CLI_DIR.rglob("*.py"))
    assert len(paths) > 10  # (the CLI's modules were found)
    assert cli_builds(paths) == []


def test_an_import_of_a_part_of_an_agent_is_found(tmp_path: Path) -> None:
    command = tmp_path / "phalanx" / "cli" / "commands" / "probe.py"
    command.parent.mkdir(parents=True)
    command.write_text(
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from phalanx.drivers.base import Driver\n"
        "def run() -> None:\n"
        "    from phalanx.drivers import open_driver, backend_names\n"
        "    from ..commands import fleet\n"
    )
    assert cli_builds([command], tmp_path) == [
        "phalanx.cli.commands.probe:3 imports phalanx.drivers.base.Driver",
        "phalanx.cli.commands.probe:5 imports phalanx.drivers.open_driver",
    ]


def agent_only_options() -> set[str]:
    """The options of `phalanx agent` that no other command has, but `--spec`: the one
    a supervisor gives it (`phalanx.runtime.process_spec.spawn_argv`).
    """
    import typer.main

    from phalanx.cli import app

    commands = typer.main.get_command(app).commands  # type: ignore[attr-defined]
    spelled = {
        name: {o for p in command.params for o in p.opts if o.startswith("-")}
        for name, command in commands.items()
    }
    others = set().union(*(opts for name, opts in spelled.items() if name != "agent"))
    return spelled["agent"] - others - {"--spec"}


def test_agents_are_started_from_a_spec_not_from_options() -> None:
    # A module that spelled an option of `phalanx agent` would be building its command
    # line by hand. The driver registry alone declares its backends' options (for the CLI).
    options = agent_only_options()
    assert {"--arcos-tcp", "--driver-setting", "--frame-timeout"} <= options
    registry = REPO / "drivers" / "__init__.py"
    hits = [
        f"{_module_name(path)}:{node.lineno} spells {node.value!r}"
        for path in _python_files()
        if not _in_cli(path) and path != registry
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Constant) and isinstance(node.value, str)
        and any(node.value == o or node.value.startswith(o + "=") for o in options)
    ]  # fmt: skip
    assert hits == []


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The groups of modules that import each other, directly or round a loop (Tarjan)."""
    order: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        order[v] = low[v] = len(order)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in order:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], order[w])
        if low[v] == order[v]:
            group = stack[stack.index(v) :]
            del stack[stack.index(v) :]
            if len(group) > 1:
                cycles.append(sorted(group))

    for v in sorted(graph):
        if v not in order:
            visit(v)
    return cycles


def test_no_modules_import_each_other() -> None:
    # What the layers contract cannot see: a loop inside one layer. (Size is kept moderate
    # by cohesion and by the duplicates tool on each change, not by a number.)
    paths = {_module_name(p): p for p in _python_files()}
    graph = {name: _imports_at_load(path, name, set(paths)) for name, path in paths.items()}
    assert sum(map(len, graph.values())) > 100  # the graph was read
    assert import_cycles(graph) == []


def test_a_loop_of_imports_is_found() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"e2"}, "e2": {"e"}}
    assert import_cycles(graph) == [["a", "b", "c"], ["e", "e2"]]


def test_an_agent_step_is_a_short_orchestration() -> None:
    agent = next(c for c in _classes(REPO / "agents" / "agent.py") if c.name == "Agent")
    step = next(n for n in agent.body if isinstance(n, ast.FunctionDef) and n.name == "step")
    lines = (step.end_lineno or step.lineno) - step.lineno + 1
    assert lines < MAX_STEP_LINES, lines


def test_nothing_in_the_repository_points_outside_it() -> None:
    # Spelled in pieces, so that this test is not itself a file naming those places.
    team = "sha" + "red"
    outside = (f"../{team}", "DES" + "IGN.md", "STY" + "LE.md", f"{team}/notes")
    hits = []
    for path in REPO.rglob("*"):
        parts = path.relative_to(REPO).parts
        if (
            not path.is_file()
            or parts[0] in (".git", ".venv", "build", "results")
            or any(p.endswith(".egg-info") or (p.startswith(".") and p != ".ci") for p in parts)
        ):
            continue
        if path.suffix not in (".py", ".md", ".toml", ".txt", ".service", "") or path == Path(
            __file__
        ):
            continue
        text = path.read_text(errors="replace")
        hits += [f"{path.relative_to(REPO)}: {o}" for o in outside if o in text]
    assert not hits, hits


def test_the_readme_shows_the_arbitration_the_transitions_generate() -> None:
    readme = (REPO / "docs" / "BEHAVIOUR.md").read_text()
    assert arbitration_markdown() in readme
