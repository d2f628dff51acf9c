"""Exit codes that tell the truth, and results that are never lost (issue 47, rows 1, 7, 8).

`phalanx up` exits non-zero (5) on a run its own metrics mark incomplete, though no
process died; a world SIGKILLed mid-run leaves the errors up to its last checkpoint; a
full disk ends `up` with one message naming the folder and what was kept, exit 6, no
traceback and no 0-byte file; a `metrics.json` already there survives a write that fails.

The full disk is real (a 300 KiB tmpfs, ENOSPC) where this user may mount one in a
namespace of its own (`unshare -rm`); the same writer is also driven past RLIMIT_FSIZE
(4 KiB per file, EFBIG, SIGXFSZ ignored; set in the child before it runs) through
`phalanx run`, which opens no Zenoh session (Zenoh's shared-memory files exceed such a
limit, so a fleet cannot run under one).
"""

from __future__ import annotations

import json
import math
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from fleetlab import CLI, WEDGE, child_running, wait_for

from phalanx.analysis.results import read_traces
from phalanx.hosts.launch import world_code
from phalanx.hosts.protocol import ChildStatus
from phalanx.runtime.exits import EXIT_FAILED, EXIT_INCOMPLETE, EXIT_RESULTS_LOST
from phalanx.runtime.local_fleet import telemetry_dir

pytestmark = pytest.mark.slow
RECORDING_B = 4096  # a telemetry part this large holds more than its header
FILE_LIMIT_B = 4096  # RLIMIT_FSIZE of the fallback full disk
# In a mount namespace of its own: a 300 KiB tmpfs at $0, the command, then what the disk
# held copied out to $KEPT (the tmpfs goes with the namespace); the command's exit code.
FULL_DISK_SH = 'mount -t tmpfs -o size=300k full "$0" && "$@"; rc=$?; cp -a "$0" "$KEPT"; exit $rc'


def _up_argv(out: Path, fleet: str, *sets: str, clock: str = "realtime") -> list[str]:
    argv = [*CLI, "up", str(WEDGE), "--out", str(out), "--fleet", fleet, "--clock", clock,
            "--timeout", "120"]  # fmt: skip
    return argv + [a for s in sets for a in ("--set", s)]


def _run_up(argv: list[str], log: Path, act: Callable[[int], None]) -> int:
    """`phalanx up` with its output to `log`; `act(pid)` while it runs; its exit code."""
    with log.open("wb") as sink:
        proc = subprocess.Popen(argv, stdout=sink, stderr=subprocess.STDOUT)
        try:
            act(proc.pid)
            return proc.wait(120)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)


def _recording(out: Path) -> bool:
    """Whether every process of the run has written telemetry past its file's header."""
    parts = {p.stem: p.stat().st_size for p in telemetry_dir(out).glob("*.rrd")}
    return set(parts) == {"world", "r1", "r2", "r3"} and min(parts.values()) > RECORDING_B


def _metrics(out: Path) -> dict[str, Any]:
    return dict(json.loads((out / "metrics.json").read_text()))


def test_up_exits_non_zero_on_a_run_its_metrics_mark_incomplete(tmp_path: Path) -> None:
    """The issue's reproduction: the leader SIGSTOPped for 4 s; nothing dies, the world
    loses sight of it, and `up` used to exit 0."""
    out = tmp_path / "up"

    def freeze_r1(up_pid: int) -> None:
        assert wait_for(lambda: _recording(out), 60.0, 0.1), "nothing recorded"
        pid = child_running(up_pid, "--robot", "r1")
        assert pid is not None
        os.kill(pid, signal.SIGSTOP)
        time.sleep(4.0)
        os.kill(pid, signal.SIGCONT)

    log = tmp_path / "up.log"
    code = _run_up(_up_argv(out, "truth-stop", "duration_s=20"), log, freeze_r1)
    text = log.read_text(errors="replace")
    metrics = _metrics(out)
    assert metrics["complete"] is False, text[-3000:]  # the world lost sight of r1
    assert "robot r1 went away" in metrics["incomplete_reason"]
    assert code == EXIT_INCOMPLETE, text[-3000:]
    assert "robot r1 went away" in text  # said, not only written
    assert "Traceback" not in text


def test_a_world_killed_mid_run_leaves_the_errors_up_to_the_kill(tmp_path: Path) -> None:
    out = tmp_path / "up"
    sets = ("duration_s=40", "initial_settle_s=1")  # errors measured from 1 s on

    def ticks_checkpointed() -> int:
        """The ticks in the world's checkpoint (0: none yet, or the run's end)."""
        try:
            metrics = _metrics(out)
        except (OSError, ValueError):
            return 0
        if not str(metrics.get("incomplete_reason")).startswith("a checkpoint of a run"):
            return 0
        return int(metrics["runtime"]["ticks_run"])

    def kill_world(up_pid: int) -> None:
        assert wait_for(lambda: ticks_checkpointed() >= 60, 60.0, 0.2), "no checkpoint"
        pid = child_running(up_pid, "world")
        assert pid is not None
        os.kill(pid, signal.SIGKILL)

    log = tmp_path / "up.log"
    code = _run_up(_up_argv(out, "truth-world", *sets), log, kill_world)
    text = log.read_text(errors="replace")
    assert code == EXIT_FAILED, text[-3000:]
    metrics = _metrics(out)
    assert metrics["complete"] is False
    assert "world: killed by SIGKILL" in metrics["incomplete_reason"]
    ticks = metrics["runtime"]["ticks_run"]
    assert 60 <= ticks < 400
    assert f"the world ran {ticks} of 400 ticks" in metrics["incomplete_reason"]
    for rid in ("r2", "r3"):  # the followers' errors, up to the last checkpoint
        forward = metrics["followers"][rid]["forward"]
        assert forward["samples"] > 0, forward
        assert math.isfinite(forward["linear_pct"]["max"])
    # The traces hold every tick the metrics count: a checkpoint writes them first, so a
    # world killed between its two files leaves traces a checkpoint ahead, never behind
    # (a .ci/run found 51 ticks of traces beside metrics of 72, written the other way).
    t_s = read_traces(out / "traces.npz")[""]["t_s"]
    assert ticks <= len(t_s) < 400
    assert t_s[ticks - 1] == pytest.approx((ticks - 1) * 0.1)
    assert "Traceback" not in text


def _namespaces_can_mount() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(
        ["unshare", "-rm", "sh", "-c", "mount -t tmpfs -o size=64k probe /mnt"],
        capture_output=True,
        timeout=10,
    )
    return probe.returncode == 0


def _ignore_sigxfsz_and_limit_files() -> None:
    """In the child: files at most FILE_LIMIT_B; writing past it fails with EFBIG."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (FILE_LIMIT_B, FILE_LIMIT_B))


def _run_on_a_full_disk(argv: list[str], disk: Path, kept: Path) -> tuple[int, str]:
    """Run `argv` (writing under `disk`) on a 300 KiB tmpfs mounted at `disk` in a user
    and mount namespace of its own; what the disk held is copied to `kept` afterwards
    (the tmpfs goes with the namespace). Exit code and output.
    """
    disk.mkdir()
    wrapped = ["unshare", "-rm", "sh", "-c", FULL_DISK_SH, str(disk), *argv]
    env = {**os.environ, "KEPT": str(kept)}
    proc = subprocess.run(wrapped, capture_output=True, timeout=180, env=env)
    return proc.returncode, (proc.stdout + proc.stderr).decode(errors="replace")


def _assert_nothing_half_written(results: Path) -> None:
    assert not list(results.glob(".*.tmp")), list(results.iterdir())
    for name in ("metrics.json", "traces.npz", "run.rrd", "fig5_trajectories.png"):
        path = results / name
        assert not path.exists() or path.stat().st_size > 0, name
    if (results / "metrics.json").exists():
        json.loads((results / "metrics.json").read_text())


@pytest.mark.skipif(
    not _namespaces_can_mount(), reason="no tmpfs can be mounted here (unshare -rm refused)"
)
def test_up_on_a_full_disk_gives_one_message_and_never_an_empty_file(tmp_path: Path) -> None:
    """The issue's reproduction: a 300 KiB tmpfs as `--out` (the processes' telemetry fills
    it first)."""
    disk, kept = tmp_path / "disk", tmp_path / "kept"
    argv = _up_argv(disk / "up", "truth-full", "duration_s=20", clock="lockstep")
    code, text = _run_on_a_full_disk(argv, disk, kept)
    assert code == EXIT_RESULTS_LOST, text[-3000:]
    assert "Traceback" not in text, text[-3000:]
    assert f"could not write metrics.json to {disk / 'up'}" in text, text[-3000:]
    kept_there = text.partition("kept there: ")[2]  # a checkpoint may be among them
    assert "telemetry/ (4 parts" in kept_there.splitlines()[0], text[-3000:]
    _assert_nothing_half_written(kept / "up")


@pytest.mark.timeout(180)  # its child processes' own bound, and set-up
def test_run_past_its_file_size_limit_gives_one_message_and_never_an_empty_file(
    tmp_path: Path,
) -> None:
    """The same writer where no tmpfs can be mounted: every file limited to 4 KiB
    (RLIMIT_FSIZE; not for a fleet, whose Zenoh sessions need larger shared-memory
    files), through `phalanx run`."""
    out = tmp_path / "run"
    argv = [*CLI, "run", str(WEDGE), "--out", str(out), "--set", "duration_s=20"]
    proc = subprocess.run(
        argv, capture_output=True, timeout=120, preexec_fn=_ignore_sigxfsz_and_limit_files
    )
    text = (proc.stdout + proc.stderr).decode(errors="replace")
    assert proc.returncode != 0, text[-3000:]
    assert "Traceback" not in text, text[-3000:]
    assert f"could not write metrics.json to {out}: File too large" in text, text[-3000:]
    _assert_nothing_half_written(out)


_MARK_ON_A_FULL_DISK = """
import sys
from pathlib import Path
from phalanx.analysis.results import ResultsNotWritten, mark_results
try:
    mark_results(Path(sys.argv[1]), problems=["x" * 10000])
except ResultsNotWritten as exc:
    print(exc)
    sys.exit(6)
"""


def test_a_metrics_file_already_there_survives_a_write_that_fails(tmp_path: Path) -> None:
    folder = tmp_path / "run"
    folder.mkdir()
    earlier = json.dumps({"runtime": {"incomplete_reason": ""}, "complete": True})
    (folder / "metrics.json").write_text(earlier)
    proc = subprocess.run(
        [sys.executable, "-c", _MARK_ON_A_FULL_DISK, str(folder)],
        capture_output=True,
        timeout=60,
        preexec_fn=_ignore_sigxfsz_and_limit_files,
    )
    assert proc.returncode == EXIT_RESULTS_LOST, proc.stderr.decode()[-2000:]
    message = proc.stdout.decode()
    assert f"could not write metrics.json to {folder}" in message
    assert "kept there: metrics.json" in message
    assert (folder / "metrics.json").read_text() == earlier  # not truncated, not replaced
    assert sorted(p.name for p in folder.iterdir()) == ["metrics.json"]


def _world(state: str, exit_code: int | None) -> ChildStatus:
    return ChildStatus(name="world", kind="world", state=state, exit_code=exit_code)  # type: ignore[arg-type]


def test_a_launch_exit_code_follows_its_world() -> None:
    assert world_code(_world("finished", 0)) == 0
    assert world_code(_world("finished", EXIT_INCOMPLETE)) == EXIT_INCOMPLETE
    assert world_code(_world("failed", EXIT_RESULTS_LOST)) == EXIT_RESULTS_LOST
    assert world_code(_world("failed", -9)) == EXIT_FAILED
    assert world_code(_world("stopped", -15)) == EXIT_FAILED
