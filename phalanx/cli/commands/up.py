"""`phalanx up`: the world and one agent process per robot on this machine, supervised."""

from __future__ import annotations

import contextlib
import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from phalanx.cli.commands.fleet import (
    ClockOpt,
    FleetOpt,
    ScenarioArg,
    SetOpt,
    _clock,
    _results_lost,
    _scenario,
    _stop_on_signals,
)
from phalanx.cli.commands.run import DpiOpt, FormatOpt, _figure_format
from phalanx.cli.numbers import seconds, speed_factor
from phalanx.cli.outputs import ForceOpt, fresh_folder, results_name
from phalanx.cli.style import choice

if TYPE_CHECKING:
    from phalanx.runtime.local_fleet import Outcome


def up(
    scenario: ScenarioArg,
    fleet: FleetOpt = "default",
    clock: ClockOpt = "lockstep",
    speed: Annotated[
        float, typer.Option(help="Real-time speed factor.", callback=speed_factor)
    ] = 1.0,
    out: Annotated[
        Path | None,
        typer.Option(help="Results folder (default: results/<scenario>-<controller>-up)."),
    ] = None,
    restart: Annotated[bool, typer.Option(help="Restart crashed agents (with back-off).")] = False,
    timeout: Annotated[
        float, typer.Option(help="Give up after this many seconds.", callback=seconds)
    ] = 600.0,
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
    robots: Annotated[
        str,
        typer.Option(
            help="Who simulates the robots: phalanx (its world process) or amrisim (one "
            "AMRISim with a P3DX per robot, driven through the arcos driver over TCP, as "
            "real robots are).",
        ),
    ] = "phalanx",
    amrisim: Annotated[
        Path | None,
        typer.Option(help="--robots amrisim: the AMRISim binary (default: $PHALANX_AMRISIM)."),
    ] = None,
    amrisim_odometry_error: Annotated[
        str,
        typer.Option(
            help="--robots amrisim: AMRISim's odometry error model: none, random_init, "
            "random_each_update or constant."
        ),
    ] = "none",
    figure_format: FormatOpt = "png",
    dpi: DpiOpt = 150,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress on stderr.")] = False,
    force: ForceOpt = False,
) -> None:
    """Start the world and one agent process per robot here; supervise; write results,
    marked complete or not (`complete` in metrics.json) with the reason. The processes
    talk over a Unix-domain socket in a directory only this user can open, made for the
    run and removed after it: no other user's process can join the fleet.

    Exit code: 0 only for a complete run; 1 when a process died or the run was stopped
    (timeout, Ctrl-C); 2 for bad input; 5 when every process ended as asked but the
    results mark the run incomplete (a robot out of the world's sight, a report that never
    came); 6 when the results could not be written (a full disk). Each names why.
    """
    from phalanx.analysis.results import ResultsNotWritten, mark_results
    from phalanx.runtime.amrisim import (
        AmrisimCommand,
        Xvfb,
        amrisim_binary,
        free_port_run,
        odometry_error,
    )
    from phalanx.runtime.local_fleet import (
        AmrisimRun,
        UpOptions,
        merge_recordings,
        plan,
        private_fabric,
        start_viewer,
        supervise,
        telemetry_dir,
    )

    choice(driver, ("sim", "arcos"), option="--driver")
    choice(robots, ("phalanx", "amrisim"), option="--robots")
    fmt = _figure_format(figure_format)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s up %(levelname)s %(message)s")
    started_unix = time.time()  # (a metrics.json older than this is an earlier run's)
    config = _scenario(scenario, set_)
    if viewer and telemetry_url is None:
        _need_display()
    if robots == "amrisim" and driver != "sim":
        raise typer.BadParameter("--robots amrisim drives AMRISim's robots: leave --driver out")
    out = fresh_folder(out or results_name(config.name, config.controller.kind, "up"), force=force)
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
        overrides=tuple(set_ or ()),
        driver=driver,
        pin=pin,
    )
    if (driver == "arcos" or robots == "amrisim") and options.clock == "lockstep":
        typer.echo("robots on drivers keep their own time: running with --clock realtime", err=True)
        options.clock = "realtime"
    with contextlib.ExitStack() as stack:
        if robots == "amrisim":
            mode, binary = odometry_error(amrisim_odometry_error), amrisim_binary(amrisim)
            display = stack.enter_context(Xvfb()).display
            command = AmrisimCommand(
                binary=binary,
                map_path=out / "amrisim.map",
                log_path=out / "amrisim.log",
                base_port=free_port_run(len(config.robots)),
                odometry_error=mode,
            )
            options.amrisim = AmrisimRun(command, display)
            typer.echo(f"AMRISim: {command.binary} (its log: {command.log_path})", err=True)
        endpoint = stack.enter_context(private_fabric())  # (only this user can join)
        logging.getLogger("phalanx.up").info("the fleet's Zenoh endpoint: %s", endpoint)
        children = plan(scenario, config, options, endpoint=endpoint)
        children[0].argv += ["--format", fmt, "--dpi", str(dpi)]  # (the world's figures)
        watch = stack.enter_context(
            RunWatch(out, config.duration_s, config.dt_s, since_unix=started_unix, quiet=quiet)
        )
        outcome = supervise(children, options, _stop_on_signals())
        watch.stop(finished=outcome.complete)
    parts = sorted(telemetry_dir(out).glob("*.rrd")) if recording else []
    if parts and merge_recordings(parts, out / "run.rrd"):
        typer.echo(f"recording: {out / 'run.rrd'} ({len(parts)} processes merged)")
    try:
        metrics = mark_results(out, problems=outcome.problems, since_unix=started_unix)
    except ResultsNotWritten as exc:
        _results_lost(exc)
    if not metrics.get("complete", False):
        typer.echo(f"results (incomplete: {metrics['incomplete_reason']}): {out}", err=True)
    else:
        typer.echo(f"results: {out}")
    raise typer.Exit(exit_code(outcome, metrics))


class RunWatch:
    """Progress of a run of processes on stderr: the world's checkpoints (`metrics.json`
    every few seconds, "N ticks run") against the scenario's duration, read on a thread
    of its own once a second. Nothing is shown before the first checkpoint.
    """

    def __init__(
        self, out: Path, duration_s: float, dt_s: float, *, since_unix: float, quiet: bool
    ) -> None:
        import threading

        from phalanx.cli.progress import Reporter

        self.out, self.duration_s, self.dt_s, self.since_unix = out, duration_s, dt_s, since_unix
        self.reporter = Reporter("up", unit="s of run", quiet=quiet, from_first=True)
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="up-progress", daemon=True)

    def __enter__(self) -> RunWatch:
        if not self.reporter.quiet:
            self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self.stop()

    def stop(self, *, finished: bool = False) -> None:
        """Stop watching (once the world has ended; `finished`: the whole run) and end
        the progress line.
        """
        if self._done.is_set():
            return
        self._done.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
            if finished:
                self.reporter(self.duration_s, self.duration_s)
        self.reporter.close()

    def _loop(self) -> None:
        while not self._done.wait(1.0):
            ran = checkpoint_s(self.out / "metrics.json", self.dt_s, since_unix=self.since_unix)
            if ran is not None:
                self.reporter(min(ran, self.duration_s), self.duration_s)


def checkpoint_s(path: Path, dt_s: float, *, since_unix: float) -> float | None:
    """The run time a world's checkpoint in `path` has reached (None if there is none
    newer than `since_unix`, or it cannot be read: a file being replaced, another's).
    """
    import json
    import re

    try:
        if path.stat().st_mtime < since_unix or path.stat().st_size > 50_000_000:
            return None
        reason = json.loads(path.read_text(encoding="utf-8")).get("incomplete_reason")
    except (OSError, ValueError, AttributeError):
        return None
    if not isinstance(reason, str):
        return None
    # "N ticks run", or the world's own "the world ran N of M ticks".
    found = re.search(r"(\d{1,12}) ticks run", reason) or re.search(
        r"ran (\d{1,12}) of \d{1,12} ticks", reason
    )
    return int(found.group(1)) * dt_s if found else None


def _need_display() -> None:
    """Exit 2 with the way out when `--viewer` cannot open a window here."""
    from phalanx.cli.commands.view import has_display

    if not has_display():
        typer.echo(
            "error: --viewer: no display here (neither DISPLAY nor WAYLAND_DISPLAY is set): "
            "start `phalanx view --web` and give its --telemetry-url instead",
            err=True,
        )
        raise typer.Exit(2)


def exit_code(outcome: Outcome, metrics: dict[str, Any]) -> int:
    """`phalanx up`'s exit code: the results not written (by the world), a process's
    death or a stop, an incomplete run by its metrics, or 0.
    """
    from phalanx.runtime.exits import EXIT_FINISHED, EXIT_INCOMPLETE, EXIT_RESULTS_LOST

    if outcome.world_code == EXIT_RESULTS_LOST:
        return EXIT_RESULTS_LOST
    if outcome.code != EXIT_FINISHED:
        return outcome.code
    return EXIT_FINISHED if metrics.get("complete") is True else EXIT_INCOMPLETE


def register(app: typer.Typer) -> None:
    """Add `phalanx up`."""
    app.command("up")(up)
