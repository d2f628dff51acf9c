"""The command line talks plainly: every verb's help keeps every word it was written with
(no Rich markup eating `[zenoh.router]`), types in plain words, `-h`, `--version`, shell
completion, verbs by task, errors naming the option and its valid values, `view` on a
headless machine pointing at `--web`, and run tables with no `nan`.
"""

from __future__ import annotations

import importlib.metadata
import re
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, get_type_hints

import pytest
import typer
from typer.models import ParameterInfo
from typer.testing import CliRunner

from phalanx.cli import app
from phalanx.cli.style import VERB_GROUPS

REPO = Path(__file__).resolve().parents[2]
SCENARIOS = REPO / "configs" / "scenarios"
# typer's own types as it prints them (`<bool>`, `<list[str]>`), not a placeholder
# written in a help text such as robot/<id>/fix
TYPER_TYPES = re.compile(r"<(bool|str|int|float|path|file|list\[[^>]*\])>")


def _verbs(typer_app: typer.Typer, prefix: tuple[str, ...] = ()) -> Iterator[Any]:
    """Every verb of `typer_app` (sub-apps' too): its command words and function."""
    for info in typer_app.registered_commands:
        assert info.name is not None
        assert info.callback is not None
        yield (*prefix, info.name), info.callback
    for group in typer_app.registered_groups:
        assert group.name is not None
        assert group.typer_instance is not None
        yield from _verbs(group.typer_instance, (*prefix, group.name))


VERBS = dict(_verbs(app))


def _written(function: Callable[..., Any]) -> list[str]:
    """The help a verb was written with: its docstring and its parameters' help."""
    texts: list[str | None] = [function.__doc__]
    for hint in get_type_hints(function, include_extras=True).values():
        texts += [m.help for m in getattr(hint, "__metadata__", ()) if isinstance(m, ParameterInfo)]
    return [t for t in texts if t]


def _plain(output: str) -> str:
    """Terminal output on one line, without box-drawing characters."""
    return " ".join(re.sub(r"[│╭╮╰╯─┃━┏┓┗┛┡┩╇┳┻┃]", " ", output).split())


def _help(*words: str) -> str:
    result = CliRunner().invoke(app, [*words, "--help"], prog_name="phalanx")
    assert result.exit_code == 0, result.output
    return result.output


def test_every_verb_is_found() -> None:
    assert {"run", "up", "view", "sweep", "mocap", "router", "emulate"} <= {v[-1] for v in VERBS}
    assert ("pki", "issue") in VERBS


@pytest.mark.parametrize("words", sorted(VERBS), ids=" ".join)
def test_help_keeps_every_written_word(words: tuple[str, ...]) -> None:
    shown = _help(*words)
    flat = _plain(shown)
    for text in _written(VERBS[words]):
        for word in text.split():
            assert word in flat, f"{' '.join(words)} --help lost {word!r}:\n{shown}"
    assert not TYPER_TYPES.search(shown), shown


def test_the_bracketed_words_of_the_issue_are_shown() -> None:
    assert "Deployment whose [zenoh.router] to serve." in _plain(_help("router"))
    assert "Scenario file: robots, [localisation.mocap]." in _plain(_help("mocap"))
    assert "wheel errors ([localisation.odometry])" in _plain(_help("emulate"))


def test_flags_show_no_type_and_lists_their_element() -> None:
    shown = _plain(_help("router"))
    assert "--listen TEXT Endpoint to listen on" in shown
    assert "--version Show phalanx's version" in shown
    assert "-h, --help Show this message" in shown


@pytest.mark.parametrize("words", [(), ("run",), ("sweep",), ("pki",), ("pki", "list")])
def test_minus_h_is_help(words: tuple[str, ...]) -> None:
    result = CliRunner().invoke(app, [*words, "-h"], prog_name="phalanx")
    assert result.exit_code == 0, result.output
    assert result.output == _help(*words)


@pytest.mark.parametrize("words", [(), ("run",), ("view",), ("pki", "issue")])
def test_version_is_the_package_version(words: tuple[str, ...]) -> None:
    result = CliRunner().invoke(app, [*words, "--version"], prog_name="phalanx")
    assert result.exit_code == 0, result.output
    assert result.output == f"phalanx {importlib.metadata.version('phalanx')}\n"


def test_shell_completion_completes_verbs() -> None:
    assert "--install-completion" in _help()
    env = {"_PHALANX_COMPLETE": "complete_bash", "COMP_WORDS": "phalanx sw", "COMP_CWORD": "1"}
    result = CliRunner().invoke(app, [], env=env, prog_name="phalanx")
    assert result.output.split() == ["sweep", "sweep-compare"]


def test_verbs_are_listed_by_task() -> None:
    shown = _help()
    titles = [title for title, _ in VERB_GROUPS]
    places = [shown.index(f"\n{title}:\n") for title in titles]
    assert places == sorted(places)
    assert "\nCommands:\n" not in shown  # every verb has its group
    order = [shown.index(f"\n  {verb} ") for verb in ("run", "up", "agent", "launch", "sweep")]
    assert order == sorted(order)
    assert "..." not in shown.partition("Run and look:")[2]  # each first sentence whole


def _error(*args: str, env: dict[str, str | None] | None = None) -> str:
    result = CliRunner().invoke(app, list(args), env=env, prog_name="phalanx")
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    return _plain(result.output)


def test_a_wrong_controller_names_the_option_and_the_controllers(tmp_path: Path) -> None:
    said = _error("run", str(SCENARIOS / "paper_wedge.toml"), "--controller", "track",
                  "--out", str(tmp_path / "out"))  # fmt: skip
    assert "'--controller'" in said
    assert "tracking, switching, icr, ours" in said
    assert "did you mean 'tracking'" in said


def test_a_wrong_family_names_the_option_and_the_families(tmp_path: Path) -> None:
    said = _error("sweep", "--family", "feild", "--seeds", "1", "--out", str(tmp_path / "r.jsonl"))
    assert "'--family'" in said
    assert "corridor, deadend, field, narrow" in said
    assert "did you mean 'field'" in said
    assert not (tmp_path / "r.jsonl").exists()


def test_a_wrong_mocap_system_names_the_option_and_the_systems() -> None:
    said = _error("mocap", str(SCENARIOS / "real_wedge.toml"), "--system", "optitrak")
    assert "'--system'" in said
    for system in ("optitrack", "vicon", "qualisys", "vrpn", "mock"):
        assert system in said
    assert "did you mean 'optitrack'" in said


@pytest.mark.parametrize("verb", ["agent", "world", "emulate"])
def test_an_epoch_that_is_not_a_time_is_refused(verb: str) -> None:
    """(a world given `--epoch nan` ran none of its ticks and said only that the run was
    incomplete)"""
    scenario = str(SCENARIOS / "paper_wedge.toml")
    args = {"agent": [scenario, "--robot", "r1"], "world": [scenario], "emulate": ["p3dx"]}
    said = _error(verb, *args[verb], "--epoch", "nan")
    assert "'--epoch'" in said
    assert "nan is not a Unix time" in said


@pytest.mark.timeout(180)  # its child processes' own bound, and set-up
def test_a_robot_file_given_as_a_scenario_is_called_one(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "phalanx", "run", str(REPO / "configs/robots/p3dx.toml"),
         "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=120, cwd=tmp_path,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert "this is a robot file" in done.stderr
    assert "configs/robots/" in done.stderr
    assert "not a scenario" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1  # not pydantic's 15 lines


def test_view_on_a_headless_machine_says_to_use_web(tmp_path: Path) -> None:
    if sys.platform in ("darwin", "win32"):
        pytest.skip("these systems always have a desktop")
    said = _error("view", env={"DISPLAY": None, "WAYLAND_DISPLAY": None})
    assert "no display here" in said
    assert "--web" in said


def test_a_run_without_a_reverse_prints_no_nan(tmp_path: Path) -> None:
    scenario = SCENARIOS / "nav_field_wedge3.toml"
    assert "reverse" not in scenario.read_text(encoding="utf-8")
    result = CliRunner().invoke(
        app,
        ["run", str(scenario), "--set", "duration_s=30", "--out", str(tmp_path / "out"),
         "--no-recording", "--no-figures", "--no-progress"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "forward" in result.output
    assert "nan" not in result.output.lower(), result.output
    assert re.search(r"^r2 +backward +- +- ", result.output, re.MULTILINE), result.output
