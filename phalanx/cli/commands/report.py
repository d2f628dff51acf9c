"""`phalanx report`: the scenario matrix and its RESULTS.md, in a results folder (or in
docs/ when asked).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from phalanx.cli.outputs import ForceOpt, fresh_folder
from phalanx.cli.tables import MarkdownOpt, show_table

REPORT_FOLDER = Path("results/report")


def report(
    docs: Annotated[
        Path | None,
        typer.Option(
            help="Rewrite RESULTS.md and figures/ in this folder, e.g. --docs docs for the "
            "repository's (default: they go into the results folder)."
        ),
    ] = None,
    out: Annotated[
        Path,
        typer.Option(help="Results folder: a folder per run (and RESULTS.md unless --docs)."),
    ] = REPORT_FOLDER,
    workers: Annotated[int, typer.Option(min=1, help="Worker processes.")] = 2,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress on stderr.")] = False,
    markdown: MarkdownOpt = False,
    force: ForceOpt = False,
) -> None:
    """Run 3 formations x 4 controllers (plus reverses while turning, and ours with noise);
    write RESULTS.md with its figures, and the wedge's runs' paper.pdf. RESULTS.md keeps
    the sections the benchmarks and the sweep wrote into docs/RESULTS.md (or the --docs
    folder's), so a results folder's and the repository's are the same bytes.
    """
    from phalanx.analysis.report import default_cases, matrix_cells, write_report
    from phalanx.cli.progress import Reporter

    out = fresh_folder(out, force=force)
    page = docs if docs is not None else out
    kept = (docs if docs is not None else Path("docs")) / "RESULTS.md"
    cases = default_cases()
    reporter = Reporter("report", unit="runs", quiet=quiet)
    results = write_report(
        page, out, workers=workers, progress=reporter, cases=cases, kept_from=kept
    )
    reporter.close()
    headers, rows = matrix_cells(cases, results)
    title = "the matrix, worst follower (✗: above the paper's bound)"
    show_table(headers, rows, title=title, markdown=markdown)
    typer.echo(f"{len(results)} runs; results: {out}; wrote {page / 'RESULTS.md'}")


def register(app: typer.Typer) -> None:
    """Add `phalanx report`."""
    app.command("report")(report)
