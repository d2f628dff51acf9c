"""`phalanx fsm`: the behaviour state machine as Mermaid text and as a PNG diagram (the
counterpart of the paper's Stateflow chart, figure 4a).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def fsm(
    png: Annotated[
        Path, typer.Option("--png", help="Where to write the diagram (PNG).", dir_okay=False)
    ] = Path("fsm.png"),
    table: Annotated[
        bool, typer.Option(help="Also print the arbitration table (markdown).")
    ] = False,
) -> None:
    """Print the behaviour state machine (navigation and formation layers) as Mermaid."""
    from phalanx.agents.behaviours.stack import (
        STATE_NOTES,
        arbitration_markdown,
        behaviour_machine,
    )
    from phalanx.agents.fsm import to_mermaid
    from phalanx.analysis.figures import save_state_machine

    machine = behaviour_machine()
    typer.echo(to_mermaid(machine, notes=STATE_NOTES), nl=False)
    if table:
        typer.echo("\n" + arbitration_markdown())
    save_state_machine(machine, png)
    typer.echo(f"diagram: {png}", err=True)


def register(app: typer.Typer) -> None:
    """Add `phalanx fsm`."""
    app.command("fsm")(fsm)
