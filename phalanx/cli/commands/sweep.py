"""`phalanx sweep`: navigation runs (family x seeds x controllers x formations x robots)
on Dask, locally or on a cluster; resumable; one table, and docs/RESULTS.md's section.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, get_args

import typer

from phalanx.cli.numbers import group_sizes
from phalanx.cli.progress import Reporter, sweep_statement
from phalanx.cli.tables import MarkdownOpt, markdown_cells, show_table

if TYPE_CHECKING:
    from phalanx.analysis.sweep import Job

# A run's wall time on one worker when the results file has none to go by: a field run
# of 3 robots took 2.2 s on average on a 2-core machine (300 runs in about 6 min on 2
# workers; 600 of 3 and 5 robots in 12.9 min).
PER_RUN_S = 2.2


def sweep(
    family: Annotated[
        list[str] | None,
        typer.Option(help="Scenario family: field, narrow, deadend, corridor (default field)."),
    ] = None,
    shape: Annotated[list[str] | None, typer.Option(help="Formations (default all three).")] = None,
    robots: Annotated[
        list[int] | None, typer.Option(help="Group sizes (default 3).", callback=group_sizes)
    ] = None,
    controller: Annotated[
        list[str] | None, typer.Option(help="Follower controllers (default ours).")
    ] = None,
    seeds: Annotated[int, typer.Option(min=1, max=100000, help="Seeds 0..N-1.")] = 100,
    first_seed: Annotated[int, typer.Option(min=0, help="First seed.")] = 0,
    workers: Annotated[int, typer.Option(min=1, max=256, help="Local worker processes.")] = 2,
    address: Annotated[
        str | None,
        typer.Option(help="A Dask scheduler (tcp://host:8786) instead of local workers."),
    ] = None,
    out: Annotated[
        Path, typer.Option(help="Results file (JSON lines; finished runs are not re-run).")
    ] = Path("results/sweep/runs.jsonl"),
    write: Annotated[bool, typer.Option(help="Rewrite docs/RESULTS.md's sweep section.")] = False,
    docs: Annotated[Path, typer.Option(help="Where RESULTS.md is.")] = Path("docs"),
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="PATH=VALUE: override a field of every run's scenario."),
    ] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress on stderr.")] = False,
    markdown: MarkdownOpt = False,
) -> None:
    """Run the sweep, print the table (and write it into docs/RESULTS.md with --write).
    Every finished run is appended to the results file, so a sweep run again does only
    what it lacks.
    """
    from phalanx.analysis import sweep as sw
    from phalanx.analysis.report import SWEEP_BEGIN, SWEEP_END, with_section
    from phalanx.core.config import ControllerKind
    from phalanx.core.config_files import parse_assignment
    from phalanx.core.errors import ConfigError
    from phalanx.core.scenarios import Course, Shape

    family = _choices(family or ["field"], get_args(Course), option="--family")
    shape = _choices(shape or list(get_args(Shape)), get_args(Shape), option="--shape")
    robots = robots or [3]
    controller = _choices(controller or ["ours"], get_args(ControllerKind), option="--controller")
    try:
        overrides = [parse_assignment(a) for a in set_ or []]
    except ConfigError as exc:
        raise typer.BadParameter(str(exc)) from exc
    try:
        todo = sw.jobs(
            family, shape, robots, range(first_seed, first_seed + seeds), controller, overrides
        )
        todo[0].scenario() if todo else None
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    reporter = Reporter("sweep", unit="runs", quiet=quiet)
    reporter.say(statement(todo, out, workers=workers, address=address))
    rows = sw.run_sweep(todo, out, address=address, workers=workers, progress=reporter)
    reporter.close()
    groups = sw.summaries(rows)
    from phalanx.analysis.report import terminal_width

    typer.echo("\n".join(sw.terminal_table(groups, width=terminal_width(), markdown=markdown)))
    wall_s = sum(r["wall_s"] for r in rows)
    typer.echo(f"{len(rows)} runs, {wall_s:.0f} s of run time; results: {out}")
    if write:
        command = (
            f"phalanx sweep --seeds {seeds} "
            + " ".join(f"--family {f}" for f in family)
            + " "
            + " ".join(f"--shape {s}" for s in shape)
            + " "
            + " ".join(f"--robots {n}" for n in robots)
            + " --workers 2 --write"
        )
        path = docs / "RESULTS.md"
        text = path.read_text(encoding="utf-8") if path.exists() else ""
        section = sw.section(command, groups)
        path.write_text(
            with_section(text, section, begin=SWEEP_BEGIN, end=SWEEP_END), encoding="utf-8"
        )
        typer.echo(f"wrote {path}")


def statement(todo: list[Job], out: Path, *, workers: int, address: str | None) -> str:
    """What the sweep says before it starts: the runs left to do and their estimated
    time, by the mean wall time of the runs `out` holds already (else `PER_RUN_S`).
    """
    from phalanx.analysis.sweep import read_rows

    have, skipped = read_rows(out)
    walls = [r["wall_s"] for r in have.values()]
    per_run = sum(walls) / len(walls) if walls else PER_RUN_S
    left = sum(1 for job in todo if job.key not in have)
    text = sweep_statement(left, per_run, workers)
    if address is not None:
        text += f" (the cluster at {address} may have more)"
    if left < len(todo):
        text += f" ({len(todo) - left} of {len(todo)} in {out} already)"
    if skipped:
        said = f"1 line of {out} holds" if skipped == 1 else f"{skipped} lines of {out} hold"
        text += f"; {said} no run's record, left out"
    return text


def _choices(values: list[str], valid: tuple[str, ...], *, option: str) -> list[str]:
    """`values`, each checked against `valid` (a usage error names `option` and them)."""
    from phalanx.cli.style import choice

    return [choice(value, valid, option=option) for value in values]


def sweep_compare(
    before: Annotated[Path, typer.Argument(help="Results file of the sweep before.")],
    after: Annotated[Path, typer.Argument(help="Results file of the sweep after.")],
    markdown: MarkdownOpt = False,
) -> None:
    """Compare two sweeps of the same fields run by run: per row, the runs each reached
    and the other did not, an exact sign test on them, and each reach's 95 % interval.
    """
    from phalanx.analysis import paired
    from phalanx.core.errors import ConfigError

    try:
        sweeps = paired.load_sweep(before), paired.load_sweep(after)
    except ConfigError as exc:
        raise typer.BadParameter(str(exc)) from exc
    for path, found in zip((before, after), sweeps, strict=True):
        if found.skipped:
            typer.echo(f"{path}: {found.skipped} lines that are not sweep runs, skipped", err=True)
    pairs = paired.compare(*sweeps)
    if not pairs:
        raise typer.BadParameter(
            "the two files share no run (same family, shape, robots, controller, seed)"
        )
    headers, rows = markdown_cells(paired.table(pairs))
    show_table(headers, rows, title=f"{before} -> {after}", markdown=markdown)


def register(app: typer.Typer) -> None:
    """Add `phalanx sweep` and `phalanx sweep-compare`."""
    app.command("sweep")(sweep)
    app.command("sweep-compare")(sweep_compare)
