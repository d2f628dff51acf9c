"""Every command shown in README.md and docs/*.md parses against the real command line:
each `phalanx ...` line of a shell code block names a verb that exists (and a sub-verb, as in
`phalanx pki issue`), only options that verb has, a value after each option that takes one,
and no more arguments than the verb takes. Nothing is run: the line goes through the option
parser of the verb's click command only, so values (files, hosts) are not checked. A
`python bench/X.py` line names a benchmark that exists (its flags are the script's own).
"""

from __future__ import annotations

import re
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import typer

from phalanx.cli import app

REPO = Path(__file__).resolve().parents[2]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
SHELL_FENCES = {"bash", "sh", "shell", "console"}
FENCE = re.compile(r"^\s*```\s*(\S*)")
ENV_ASSIGNMENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")
SEPARATORS = {"&&", "||", ";", "|", "&", "(", ")"}
# A token standing for "and so on": dropped, it is no argument of the verb.
ELLIPSES = {"...", "…"}


@dataclass(frozen=True)
class DocCommand:
    """One command of a shell code block: where it is and its words after the program."""

    where: str  # "docs/HOSTS.md:13"
    program: str  # "phalanx" or "python"
    words: tuple[str, ...]


def _logical_lines(block: list[tuple[int, str]]) -> list[tuple[int, str]]:
    """The lines of one code block, those continued with a trailing backslash joined,
    each with the number of the line it starts on."""
    joined: list[tuple[int, str]] = []
    start = 0
    parts: list[str] = []
    for number, line in block:
        if not parts:
            start = number
        stripped = line.rstrip()
        parts.append(stripped.removesuffix("\\"))
        if not stripped.endswith("\\"):
            joined.append((start, " ".join(parts)))
            parts = []
    if parts:
        joined.append((start, " ".join(parts)))
    return joined


def _shell_blocks(page: Path) -> list[list[tuple[int, str]]]:
    """The shell code blocks of `page`: their lines, each with its line number."""
    blocks: list[list[tuple[int, str]]] = []
    inside, shell = False, False
    for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
        fence = FENCE.match(line)
        if fence is not None:
            inside, shell = not inside, fence.group(1).lower() in SHELL_FENCES
            if inside and shell:
                blocks.append([])
        elif inside and shell:
            blocks[-1].append((number, line))
    return blocks


def _simple_commands(line: str) -> list[list[str]]:
    """The words of each simple command of a shell line (split at `&&`, `|`, `;`, `&`),
    with `# comments`, leading `VAR=value` assignments and `sudo` removed."""
    lexer = shlex.shlex(line, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    lexer.commenters = "#"
    commands: list[list[str]] = [[]]
    for token in lexer:
        if token in SEPARATORS:
            commands.append([])
        else:
            commands[-1].append(token)
    cleaned = []
    for words in commands:
        while words and (ENV_ASSIGNMENT.match(words[0]) or words[0] == "sudo"):
            words = words[1:]
        if words:
            cleaned.append(words)
    return cleaned


def _command(where: str, words: list[str]) -> DocCommand | None:
    """The phalanx or benchmark command `words` are, or None for any other program."""
    program = words[0]
    if program == "phalanx" or program.endswith("/bin/phalanx"):
        rest = [w[1:-1] if re.fullmatch(r"\[-.*\]", w) else w for w in words[1:]]
        return DocCommand(where, "phalanx", tuple(w for w in rest if w not in ELLIPSES))
    if re.fullmatch(r"(.*/)?python3?", program) and words[1:2] and words[1].startswith("bench/"):
        return DocCommand(where, "python", tuple(words[1:]))
    return None


def doc_commands() -> list[DocCommand]:
    """Every phalanx and benchmark command in the shell code blocks of the docs."""
    found: list[DocCommand] = []
    for page in PAGES:
        name = page.relative_to(REPO).as_posix()
        for block in _shell_blocks(page):
            for number, line in _logical_lines(block):
                for words in _simple_commands(line):
                    command = _command(f"{name}:{number}", words)
                    if command is not None:
                        found.append(command)
    return found


def _context(command: Any, name: str, parent: Any) -> Any:
    """A context for `command` as click builds one, without parsing anything."""
    return command.context_class(command, info_name=name, parent=parent, **command.context_settings)


def parse_problem(words: tuple[str, ...]) -> str | None:
    """Why `phalanx WORDS` would not parse (an unknown verb or option, an option without
    its value, an argument too many), or None when it parses. Nothing is invoked and no
    value is converted, so files named need not exist."""
    command: Any = typer.main.get_command(app)
    ctx = _context(command, "phalanx", None)
    args = list(words)
    path = "phalanx"
    try:
        while True:
            _, rest, _ = command.make_parser(ctx).parse_args(args=args)
            if not hasattr(command, "get_command"):  # a verb: every argument consumed?
                if rest:
                    return f"`{path}` got unexpected argument(s): {' '.join(rest)}"
                return None
            if not rest:  # a group and options only (`phalanx --help`, `phalanx --version`)
                return None
            verb, args = rest[0], rest[1:]
            sub = command.get_command(ctx, verb)
            if sub is None:
                known = ", ".join(command.list_commands(ctx))
                return f"`{path}` has no verb {verb!r} (verbs: {known})"
            command, path = sub, f"{path} {verb}"
            ctx = _context(command, verb, ctx)
    except Exception as exc:  # click's usage errors (typer vendors click privately)
        message = getattr(exc, "format_message", exc.__str__)()
        return f"`{path}`: {message}"


COMMANDS = doc_commands()
PHALANX = [c for c in COMMANDS if c.program == "phalanx"]
BENCHES = [c for c in COMMANDS if c.program == "python"]


def test_the_docs_show_commands_of_every_kind() -> None:
    """The extraction finds the docs' commands: the quick start, a sub-verb, a benchmark."""
    shown = {c.words[:2] for c in PHALANX}
    assert ("pki", "issue") in shown
    assert any(c.where.startswith("README.md:") and c.words[:1] == ("run",) for c in PHALANX)
    assert len(PHALANX) >= 40
    assert len(BENCHES) >= 20


@pytest.mark.parametrize(
    ("words", "problem"),
    [
        (("run", "x.toml", "--no-such-flag"), "No such option"),
        (("fly", "x.toml"), "no verb 'fly'"),
        (("pki", "forge", "pki/lab"), "no verb 'forge'"),
        (("run", "x.toml", "--controller"), "requires an argument"),
        (("run", "a.toml", "b.toml"), "unexpected argument"),
    ],
)
def test_a_stale_command_is_caught(words: tuple[str, ...], problem: str) -> None:
    found = parse_problem(words)
    assert found is not None
    assert problem in found


def test_a_current_command_parses_without_its_files() -> None:
    assert parse_problem(("run", "no/such/file.toml", "--controller", "tracking")) is None
    assert parse_problem(("pki", "issue", "pki/lab", "operator.carol", "--days", "30")) is None
    assert parse_problem(("-h",)) is None
    assert parse_problem(("--version",)) is None


@pytest.mark.parametrize("command", PHALANX, ids=[c.where for c in PHALANX])
def test_every_phalanx_command_in_the_docs_parses(command: DocCommand) -> None:
    problem = parse_problem(command.words)
    assert problem is None, f"{command.where}: phalanx {' '.join(command.words)}\n  {problem}"


@pytest.mark.parametrize("command", BENCHES, ids=[c.where for c in BENCHES])
def test_every_benchmark_in_the_docs_exists(command: DocCommand) -> None:
    scripts = [w for w in command.words if re.fullmatch(r"bench/\S+\.py", w)]
    assert scripts
    missing = [s for s in scripts if not (REPO / s).is_file()]
    assert not missing, f"{command.where}: no such benchmark {missing}"
