"""`phalanx export`: a finished run's results folder in another tool's format."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

ResultsArg = Annotated[
    Path, typer.Argument(help="A run's results folder (metrics.json, traces.npz).", file_okay=False)
]


def export(
    results: ResultsArg,
    mcap: Annotated[
        bool, typer.Option("--mcap", help="A rosbag2 bag in MCAP storage (ROS 2 messages).")
    ] = False,
    scenario: Annotated[
        Path | None,
        typer.Option(
            help="The run's scenario: adds the sonar mounts (/tf_static) and the slots and "
            "obstacles (markers), and its [ros2] names the topics.",
            exists=True,
            dir_okay=False,
        ),
    ] = None,
    out: Annotated[
        Path | None, typer.Option("--out", "-o", help="The bag's folder (default RESULTS/rosbag2).")
    ] = None,
) -> None:
    """Write RESULTS as ROS 2 messages in an MCAP bag (ros2 bag, Foxglove, PlotJuggler)."""
    from phalanx.core.config import Ros2Config
    from phalanx.core.config_files import load_robot, load_scenario
    from phalanx.ros2.export import BAG_NAME, Extras, RunTraces, scenario_of_folder, write_bag

    if not mcap:
        raise typer.BadParameter("choose a format: --mcap", param_hint="'--mcap'")
    record = RunTraces.from_folder(results)
    extras, cfg = None, Ros2Config()
    if scenario is not None:
        config = load_scenario(scenario)
        recorded = scenario_of_folder(results)
        if recorded and recorded != config.name:
            typer.echo(f"export: {results} is a run of {recorded!r}, not {config.name!r}", err=True)
        extras, cfg = Extras.of(config, load_robot(config.robot)), config.ros2
    bag = out or results / BAG_NAME
    counts = write_bag(record, bag, cfg=cfg, extras=extras)
    typer.echo(f"{sum(counts.values())} messages on {len(counts)} topics: {bag}")


def register(app: typer.Typer) -> None:
    """Add `phalanx export`."""
    app.command("export")(export)
