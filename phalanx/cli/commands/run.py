"""`phalanx run`: a whole scenario in one process, with a results folder."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, get_args

import typer

from phalanx.analysis.figure_files import DPI_MAX, DPI_MIN
from phalanx.cli.outputs import ForceOpt, fresh_folder, results_name
from phalanx.cli.style import choice

if TYPE_CHECKING:
    from phalanx.analysis.figure_files import FigureFormat
    from phalanx.core.config import ControllerKind
    from phalanx.core.runlog import RunLog

ScenarioArg = Annotated[
    Path, typer.Argument(help="Scenario TOML file.", exists=True, dir_okay=False)
]
OutOpt = Annotated[
    Path | None,
    typer.Option("--out", "-o", help="Results folder (default: results/<scenario>-<controller>)."),
]
ControllerOpt = Annotated[
    str | None, typer.Option(help="Override the controller: tracking, switching, icr, ours.")
]
FormatOpt = Annotated[
    str,
    typer.Option("--format", help="The figures' file format: png, pdf or svg (vector)."),
]
DpiOpt = Annotated[
    int,
    typer.Option(
        min=DPI_MIN, max=DPI_MAX, help=f"The PNG figures' pixels per inch ({DPI_MIN}-{DPI_MAX})."
    ),
]
SetOpt = Annotated[
    list[str] | None,
    typer.Option("--set", help="Override a field, e.g. --set noise.sonar_std_m=0.02 (repeatable)."),
]


def run(
    scenario: ScenarioArg,
    out: OutOpt = None,
    controller: ControllerOpt = None,
    set_: SetOpt = None,
    recording: Annotated[bool, typer.Option(help="Write a Rerun .rrd of the run.")] = True,
    figures: Annotated[bool, typer.Option(help="Draw the figures (a step of its own).")] = True,
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
    figure_format: FormatOpt = "png",
    dpi: DpiOpt = 150,
    force: ForceOpt = False,
    mcap: Annotated[
        bool, typer.Option("--mcap", help="Also write the run as ROS 2 messages in an MCAP bag.")
    ] = False,
) -> None:
    """Run SCENARIO with every robot in this process; write metrics, figures and a recording."""
    from phalanx.analysis.report import print_summary
    from phalanx.analysis.results import write_results
    from phalanx.core.config_files import apply_overrides, load_scenario
    from phalanx.runtime.batch import run_batch

    fmt = _figure_format(figure_format)
    config = load_scenario(scenario)
    overrides = list(set_ or [])
    if controller is not None:
        overrides.append(f'controller.kind="{_controller(controller)}"')
    config = apply_overrides(config, overrides, source=str(scenario)) if overrides else config
    named = out or results_name(config.name, config.controller.kind)
    log = run_batch(config, progress=_progress_bar() if progress else None)
    folder = fresh_folder(named, force=force)
    metrics = write_results(
        log, folder, recording=recording, figures=figures, figure_format=fmt, dpi=dpi
    )
    print_summary(metrics)
    if mcap:
        _export_mcap(log, folder)
    typer.echo(f"results: {folder}")


def _export_mcap(log: RunLog, folder: Path) -> None:
    """The run as a rosbag2 MCAP bag in `folder`/rosbag2 (docs/ROS2.md)."""
    from phalanx.ros2.export import BAG_NAME, Extras, RunTraces, write_bag

    bag = folder / BAG_NAME
    extras = Extras.of(log.scenario, log.robot)
    counts = write_bag(RunTraces.from_log(log), bag, cfg=log.scenario.ros2, extras=extras)
    typer.echo(f"mcap: {sum(counts.values())} messages on {len(counts)} topics in {bag}")


def _controller(name: str) -> ControllerKind:
    from phalanx.core.config import ControllerKind

    valid: tuple[ControllerKind, ...] = get_args(ControllerKind)
    choice(name, valid, option="--controller")
    return next(kind for kind in valid if kind == name)


def _figure_format(name: str) -> FigureFormat:
    from phalanx.analysis.figure_files import FORMATS

    choice(name, FORMATS, option="--format")
    return next(fmt for fmt in FORMATS if fmt == name)


def _progress_bar() -> Callable[[int, int], None]:
    from rich.progress import Progress

    bar = Progress(transient=True)
    task = bar.add_task("simulating", total=None)

    def update(done: int, total: int) -> None:
        if done == 1:
            bar.start()
        bar.update(task, completed=done, total=total)
        if done == total:
            bar.stop()

    return update


def register(app: typer.Typer) -> None:
    """Add `phalanx run`."""
    app.command("run")(run)
