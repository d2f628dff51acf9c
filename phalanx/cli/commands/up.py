"""`phalanx up`: the world and one agent process per robot on this machine, supervised."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

from phalanx.cli.commands.fleet import (
    ClockOpt,
    FleetOpt,
    ScenarioArg,
    SetOpt,
    _clock,
    _scenario,
    _stop_on_signals,
)


def up(
    scenario: ScenarioArg,
    fleet: FleetOpt = "default",
    clock: ClockOpt = "lockstep",
    speed: Annotated[float, typer.Option(min=0.01, help="Real-time speed factor.")] = 1.0,
    out: Annotated[Path | None, typer.Option(help="Results folder.")] = None,
    restart: Annotated[bool, typer.Option(help="Restart crashed agents (with back-off).")] = False,
    timeout: Annotated[float, typer.Option(help="Give up after this many seconds.")] = 600.0,
    recording: Annotated[bool, typer.Option(help="Write a Rerun .rrd.")] = True,
    set_: SetOpt = None,
    driver: Annotated[
        str,
        typer.Option(help="sim, or arcos: every robot an ARCOS emulator moved by the world."),
    ] = "sim",
    viewer: Annotated[
        bool, typer.Option(help="Open the Rerun viewer and stream the run to it live.")
    ] = False,
    telemetry_url: Annotated[
        str | None,
        typer.Option(help="Stream live to a running viewer, e.g. from `phalanx view --web`."),
    ] = None,
    pin: Annotated[
        bool | None,
        typer.Option(
            "--pin/--no-pin",
            help="Pin each process to one CPU, round robin (default: in lockstep only).",
        ),
    ] = None,
) -> None:
    """Start the world and one agent process per robot here; supervise; write results
    (marked incomplete, with the reason, when a process died or the world did not finish;
    the exit code is then 1).
    """
    from phalanx.analysis.results import mark_results
    from phalanx.runtime.local_fleet import (
        UpOptions,
        merge_recordings,
        plan,
        start_viewer,
        supervise,
        telemetry_dir,
    )

    logging.basicConfig(level=logging.INFO, format="%(asctime)s up %(levelname)s %(message)s")
    config = _scenario(scenario, set_)
    out = out or Path("results") / f"{config.name}-{config.controller.kind}-up"
    if viewer and telemetry_url is None:
        telemetry_url = start_viewer()
    options = UpOptions(
        fleet=fleet,
        clock=_clock(clock),
        speed=speed,
        out=out,
        telemetry_url=telemetry_url,
        restart=restart,
        timeout_s=timeout,
        recording=recording,
        overrides=tuple(f"--set={o}" for o in set_ or ()),
        driver=driver,
        pin=pin,
    )
    if driver not in ("sim", "arcos"):
        raise typer.BadParameter(f"up runs sim or arcos robots, not {driver!r}")
    if driver == "arcos" and options.clock == "lockstep":
        typer.echo("arcos robots keep their own time: running with --clock realtime", err=True)
        options.clock = "realtime"
    outcome = supervise(plan(scenario, config, options), options, _stop_on_signals())
    parts = sorted(telemetry_dir(out).glob("*.rrd")) if recording else []
    if parts and merge_recordings(parts, out / "run.rrd"):
        typer.echo(f"recording: {out / 'run.rrd'} ({len(parts)} processes merged)")
    metrics = mark_results(out, problems=outcome.problems)
    if not metrics.get("complete", False):
        typer.echo(f"results (incomplete: {metrics['incomplete_reason']}): {out}", err=True)
    raise typer.Exit(outcome.code)


def register(app: typer.Typer) -> None:
    """Add `phalanx up`."""
    app.command("up")(up)
