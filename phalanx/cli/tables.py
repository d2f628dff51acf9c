"""Tables a command prints: fitted to the terminal (`phalanx.analysis.report.text_table`:
side by side when the columns fit, a `field: value` block per row when not; 80 columns in
a pipe or a CI log), plain text unless `--markdown` is given, no `nan`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated

import typer

MarkdownOpt = Annotated[
    bool,
    typer.Option(
        "--markdown", help="Print tables as Markdown (pipes) instead of fitting the terminal."
    ),
]


def show_table(
    headers: Sequence[str],
    rows: Sequence[Sequence[object]],
    *,
    title: str = "",
    markdown: bool = False,
) -> None:
    """Print a table on stdout, fitted to its width (Markdown if asked)."""
    from phalanx.analysis.report import terminal_width, text_table

    lines = text_table(headers, rows, width=terminal_width(), markdown=markdown, title=title)
    typer.echo("\n".join(lines))


def markdown_cells(lines: Sequence[str]) -> tuple[list[str], list[list[str]]]:
    """The headers and rows of a Markdown table (its alignment line skipped)."""
    rows = [
        [cell.strip() for cell in line.strip().strip("|").split("|")]
        for line in lines
        if line.strip().startswith("|")
    ]
    body = [r for r in rows[1:] if not all(set(c) <= set("-:") and c for c in r)]
    return (rows[0] if rows else []), body
