"""`phalanx fsm`: the behaviour state machine as Mermaid text, and as a picture laid out
by Graphviz (PNG and SVG; the counterpart of the paper's Stateflow chart, figure 4a).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def fsm(
    png: Annotated[
        Path, typer.Option("--png", help="Where to write the picture (PNG).", dir_okay=False)
    ] = Path("fsm.png"),
    svg: Annotated[
        Path | None,
        typer.Option("--svg", help="Also write the picture as SVG here.", dir_okay=False),
    ] = None,
    dot: Annotated[
        Path | None,
        typer.Option("--dot", help="Also write the Graphviz source here.", dir_okay=False),
    ] = None,
    table: Annotated[
        bool, typer.Option(help="Also print the arbitration table (markdown).")
    ] = False,
) -> None:
    """Print the behaviour state machine as Mermaid and draw it: states grouped in boxes,
    edges labelled with their guards, the paper's states highlighted.
    """
    from phalanx.agents.behaviours.stack import (
        STATE_NOTES,
        arbitration_markdown,
        behaviour_machine,
    )
    from phalanx.agents.fsm import to_mermaid
    from phalanx.analysis.fsm_picture import save_fsm_picture

    machine = behaviour_machine()
    typer.echo(to_mermaid(machine, notes=STATE_NOTES), nl=False)
    if table:
        typer.echo("\n" + arbitration_markdown())
    for path in save_fsm_picture(machine, png=png, svg=svg, dot=dot):
        typer.echo(f"diagram: {path}", err=True)


def register(app: typer.Typer) -> None:
    """Add `phalanx fsm`."""
    app.command("fsm")(fsm)
