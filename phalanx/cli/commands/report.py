"""`phalanx report`: the scenario matrix and docs/RESULTS.md."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def report(
    docs: Annotated[Path, typer.Option(help="Where RESULTS.md and figures/ go.")] = Path("docs"),
    out: Annotated[Path, typer.Option(help="Results folders of every run.")] = Path(
        "results/report"
    ),
    workers: Annotated[int, typer.Option(min=1, help="Worker processes.")] = 2,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress on stderr.")] = False,
) -> None:
    """Run 3 formations x 4 controllers (plus ours with noise); write docs/RESULTS.md."""
    from phalanx.analysis.report import write_report
    from phalanx.cli.progress import Reporter

    reporter = Reporter("report", unit="runs", quiet=quiet)
    results = write_report(docs, out, workers=workers, progress=reporter)
    reporter.close()
    typer.echo(f"{len(results)} runs; wrote {docs / 'RESULTS.md'}")


def register(app: typer.Typer) -> None:
    """Add `phalanx report`."""
    app.command("report")(report)
