"""The code style gates (ruff, the ruff formatter, mypy --strict) run as tests, so CI
enforces them."""

from __future__ import annotations

import ast
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent


@pytest.mark.parametrize(
    "argv",
    [
        ["ruff", "check", "."],
        ["ruff", "format", "--check", "."],
        ["mypy", "-p", "phalanx"],
    ],
    ids=["ruff-check", "ruff-format", "mypy-strict"],
)
@pytest.mark.timeout(360)  # its child processes' own bound, and set-up
def test_quality_gate(argv: list[str]) -> None:
    tool = BIN / argv[0]
    if not tool.exists():
        pytest.skip(f"{argv[0]} is not installed in this environment (install '.[dev]')")
    proc = subprocess.run(
        [str(tool), *argv[1:]], cwd=REPO, capture_output=True, text=True, timeout=300, check=False
    )
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]


# pytest-timeout's `timeout` in pyproject.toml: the bound of a test without a marker.
DEFAULT_TIMEOUT_S = float(
    tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]["timeout"]
)


def _timeout_marker(decorators: list[ast.expr]) -> float | None:
    """The seconds of a `pytest.mark.timeout(N)` among `decorators` (or a pytestmark list)."""
    for node in decorators:
        for call in ast.walk(node):
            if (
                isinstance(call, ast.Call)
                and isinstance(call.func, ast.Attribute)
                and call.func.attr == "timeout"
                and call.args
                and isinstance(call.args[0], ast.Constant)
            ):
                return float(call.args[0].value)
    return None


def _longest_inner_wait_s(test: ast.FunctionDef) -> float:
    """The largest literal `timeout=` a test passes to what it calls (subprocess.run, ...)."""
    waits = [
        float(k.value.value)
        for k in ast.walk(test)
        if isinstance(k, ast.keyword)
        and k.arg == "timeout"
        and isinstance(k.value, ast.Constant)
        and isinstance(k.value.value, int | float)
    ]
    return max(waits, default=0.0)


def test_no_test_waits_longer_than_its_own_timeout() -> None:
    """A test whose child process may take longer than pytest-timeout gives it dies in
    pytest-timeout's stack dump, not in the test's own message: each test's bound (its
    marker, its module's, or the default) must exceed the longest wait it asks for.
    """
    too_short = []
    for path in sorted((REPO / "tests").rglob("test_*.py")):
        tree = ast.parse(path.read_text())
        module_marks = [
            node.value
            for node in tree.body
            if isinstance(node, ast.Assign)
            and any(isinstance(t, ast.Name) and t.id == "pytestmark" for t in node.targets)
        ]
        module_s = _timeout_marker(module_marks) or DEFAULT_TIMEOUT_S
        for test in ast.walk(tree):
            if not (isinstance(test, ast.FunctionDef) and test.name.startswith("test_")):
                continue
            bound_s = _timeout_marker(test.decorator_list) or module_s
            inner_s = _longest_inner_wait_s(test)
            if inner_s >= bound_s:
                too_short.append(f"{path.relative_to(REPO)}::{test.name}: {bound_s} <= {inner_s}")
    assert not too_short, "\n".join(too_short)
