"""The architecture's rules as tests: the import contract between layers, the size of
classes and modules, a repository that stands on its own, and the README's arbitration
table equal to the one the transitions generate.
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

REPO = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
PACKAGE_DIRS = ("phalanx", "agents", "drivers", "simulator")
MAX_METHODS = 25
MAX_CLASS_LINES = 400
MAX_KERNEL_MODULE_LINES = 450
MAX_STEP_LINES = 40


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


def test_no_class_is_too_big() -> None:
    too_big = []
    for path in _python_files():
        for cls in _classes(path):
            methods = [n for n in cls.body if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)]
            lines = (cls.end_lineno or cls.lineno) - cls.lineno + 1
            if len(methods) > MAX_METHODS or lines > MAX_CLASS_LINES:
                too_big.append(
                    f"{path.relative_to(REPO)}::{cls.name} {len(methods)} methods, {lines} lines"
                )
    assert not too_big, too_big


def test_no_kernel_module_is_too_big() -> None:
    too_big = {
        str(p.relative_to(REPO)): n
        for p in (REPO / "phalanx").rglob("*.py")
        if p.is_file() and (n := len(p.read_text().splitlines())) > MAX_KERNEL_MODULE_LINES
    }
    assert not too_big, too_big


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
    readme = (REPO / "README.md").read_text()
    assert arbitration_markdown() in readme
