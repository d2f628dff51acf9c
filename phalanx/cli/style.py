"""How the `phalanx` command line presents itself: verbs grouped by task, help text shown
as written, plain types, `--version` on every verb, and errors that name the option and
its valid values.

Help strings and docstrings are plain text, and the app renders them as such (typer's
`rich_markup_mode=None`, click's formatter): Rich markup would take a bracketed word such
as `[zenoh.router]` for a style tag and drop it, and Rich's option tables cut long words
short ("$PHALANX_AMRI…") at 80 columns, where click's formatter wraps whole words, in a
terminal, a pipe or a CI log alike. Should the mode be Rich again, the classes here escape
the markup and join each paragraph's lines, and the task groups become Rich panels. Types
are click's plain words (TEXT, FLOAT, PATH, the choices); flags show none.
"""

from __future__ import annotations

import difflib
import inspect
from collections.abc import Iterable
from typing import Any

import typer
from typer._click import (  # (the classes typer's own take; typer is pinned to 0.29)
    Context,
    HelpFormatter,
)
from typer.core import TyperArgument, TyperCommand, TyperGroup, TyperOption

import phalanx

# The verbs by task, in the order a user meets them; a verb not named here goes last,
# with the tools.
VERB_GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("Run and look", ("run", "up", "view")),
    ("Fleets and robots", ("agent", "world", "emulate", "mocap", "ros2")),
    ("Deploy on hosts", ("launch", "status", "stop", "host", "router", "pki")),
    ("Analyse", ("report", "sweep", "sweep-compare", "export")),
    ("Tools", ("validate", "fsm")),
)
_TOOLS = VERB_GROUPS[-1][0]
_SUMMARY_CHARS = 300  # a verb's summary in the list: its first sentence, up to this
_PLAIN_NAMES = {int: "INTEGER", float: "FLOAT", str: "TEXT", bool: "BOOLEAN"}


def verb_panel(name: str) -> str:
    """The task group a verb of `phalanx` is listed under."""
    return next((title for title, verbs in VERB_GROUPS if name in verbs), _TOOLS)


def verb_order(name: str) -> tuple[int, int, str]:
    """Sort key of a verb: its group's place, then its place in the group."""
    for group, (_, verbs) in enumerate(VERB_GROUPS):
        if name in verbs:
            return group, verbs.index(name), name
    return len(VERB_GROUPS), 0, name


def literal_text(text: str | None) -> str | None:
    """Plain help text made safe for Rich markup: each paragraph on one line (the
    terminal wraps it), every bracket shown as written.
    """
    if not text:
        return text
    from rich.markup import escape

    paragraphs = inspect.cleandoc(text).split("\n\n")
    joined = [p if p.startswith("\b") else " ".join(p.split()) for p in paragraphs]
    return escape("\n\n".join(joined))


def plain_type(param: TyperOption | TyperArgument) -> str | None:
    """The value's type in click's plain words (TEXT, FLOAT, PATH, a|b|c); None for a flag."""
    if isinstance(param, TyperOption) and param.is_flag:
        return None
    if param.metavar is not None:
        return param.metavar
    described = param.type_descriptor
    if described.is_choice:
        return "|".join(str(choice) for choice in described.choices or ())
    if described.is_path:
        return "PATH"
    annotation: Any = described.annotation
    if described.is_list:
        (annotation,) = getattr(annotation, "__args__", (str,))
    return _PLAIN_NAMES.get(annotation, getattr(annotation, "__name__", "VALUE").upper())


class _PlainOption(TyperOption):
    def display_type_rich(self, ctx: Context) -> str | None:
        return plain_type(self)


class _PlainArgument(TyperArgument):
    def display_type_rich(self, ctx: Context) -> str | None:
        return plain_type(self)


def _show_version(ctx: Context, _param: object, value: bool) -> None:
    if value and not ctx.resilient_parsing:
        typer.echo(f"phalanx {phalanx.__version__}")
        ctx.exit()


def _version_option() -> TyperOption:
    from typer._coercion import bool_flag_type_descriptor  # (typer is pinned to 0.29)

    return _PlainOption(
        param_decls=["--version"],
        is_flag=True,
        expose_value=False,
        is_eager=True,
        help="Show phalanx's version and exit.",
        callback=_show_version,
        type_descriptor=bool_flag_type_descriptor(),
    )


def _present(command: TyperCommand | TyperGroup) -> None:
    """Escape the help of `command` and its parameters (Rich markup mode) and add
    `--version`.
    """
    if command.rich_markup_mode == "rich":
        command.help = literal_text(command.help)
        for param in command.params:
            if isinstance(param, TyperOption | TyperArgument):
                param.help = literal_text(param.help)
    if not any("--version" in p.opts for p in command.params):
        command.params.append(_version_option())


def _plain(params: Iterable[Any]) -> None:
    """Show every parameter's type in plain words (the help option's too)."""
    for param in params:
        if type(param) is TyperOption:
            param.__class__ = _PlainOption
        elif type(param) is TyperArgument:
            param.__class__ = _PlainArgument


class PhalanxCommand(TyperCommand):
    """A `phalanx` verb: help shown as written, plain types, `--version`."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        _present(self)

    def get_params(self, ctx: Context) -> list[Any]:  # noqa: D102
        params = super().get_params(ctx)
        _plain(params)
        return params


class PlainGroup(TyperGroup):
    """A group of verbs (`phalanx pki`): help shown as written, plain types, `--version`,
    and each verb's first sentence in the list, wrapped rather than cut short.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        _present(self)
        for name, command in self.commands.items():
            if not isinstance(getattr(command, "rich_help_panel", None), str):
                command.rich_help_panel = self.heading(name)  # type: ignore[attr-defined]

    def heading(self, verb: str) -> str:
        """The heading `verb` is listed under."""
        return "Commands"

    def format_commands(self, ctx: Context, formatter: HelpFormatter) -> None:
        """The verbs under their headings, each with its first sentence."""
        sections: dict[str, list[tuple[str, str]]] = {}
        for name in self.list_commands(ctx):
            command = self.get_command(ctx, name)
            if command is not None and not command.hidden:
                summary = command.get_short_help_str(limit=_SUMMARY_CHARS)
                sections.setdefault(self.heading(name), []).append((name, summary))
        for title, rows in sections.items():
            with formatter.section(title):
                formatter.write_dl(rows)

    def get_params(self, ctx: Context) -> list[Any]:  # noqa: D102
        params = super().get_params(ctx)
        _plain(params)
        return params


class PhalanxGroup(PlainGroup):
    """The `phalanx` app: its verbs listed by task (`VERB_GROUPS`), in that order."""

    def heading(self, verb: str) -> str:  # noqa: D102
        return verb_panel(verb)

    def list_commands(self, ctx: Context) -> list[str]:  # noqa: D102
        return sorted(self.commands, key=verb_order)


def use_everywhere(app: typer.Typer) -> None:
    """Make every command of `app` (and of its sub-apps) a `PhalanxCommand`, every
    sub-app a `PlainGroup`.
    """
    for info in app.registered_commands:
        if info.cls in (None, TyperCommand):
            info.cls = PhalanxCommand
    for group in app.registered_groups:
        group.cls = PlainGroup
        if group.typer_instance is not None:
            use_everywhere(group.typer_instance)


def choice(value: str, valid: Iterable[str], *, option: str) -> str:
    """`value` if it is one of `valid`, else a usage error naming `option`, the valid
    values and the closest one.
    """
    names = list(valid)
    if value in names:
        return value
    close = difflib.get_close_matches(value, names, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    raise typer.BadParameter(
        f"{value!r} is not one of {', '.join(names)}{hint}", param_hint=f"'{option}'"
    )
