"""A sweep of 2 004 fields on a Dask cluster of two workers on this machine, one of them
killed mid-way, then the same sweep started again.

    .venv/bin/python bench/bench_sweep_cluster.py [--seeds 334] [--kill-at 0.3] [--out FILE]

A `dask scheduler` and two `dask worker`s (one process and one thread each) run as
separate processes on loopback, as they would on other hosts. `phalanx sweep --address`
runs the field family: three formations x 3 and 5 robots x `--seeds` seeds. Once
`--kill-at` of the runs are in the results file, one worker and its nanny get SIGKILL (a
host lost) and a new worker takes its place. The benchmark prints the sweep's wall time,
the runs in the file (each must be there once), how many were in before the kill, the
sweep's first estimate and its last progress line, and what the same command does when
started again (it must run nothing), beside the calibration.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from calibration import Calibration

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "lab"))
from dask_cluster import BIN, Cluster, result_keys

SHAPES = ("wedge", "inline", "collateral")
ROBOTS = (3, 5)


def sweep_command(address: str, seeds: int, out: Path) -> list[str]:
    """`phalanx sweep` of the field family against the scheduler at `address`."""
    shapes = [a for s in SHAPES for a in ("--shape", s)]
    robots = [a for n in ROBOTS for a in ("--robots", str(n))]
    return [
        str(BIN / "phalanx"), "sweep", "--family", "field", *shapes, *robots,
        "--seeds", str(seeds), "--address", address, "--out", str(out),
    ]  # fmt: skip


def progress_lines(said: Path) -> list[str]:
    """The sweep's progress lines on stderr (it redraws one line with carriage returns)."""
    text = said.read_text(encoding="utf-8", errors="replace").replace("\r", "\n")
    return [line.strip() for line in text.splitlines() if line.strip()]


def main() -> None:
    """Run the sweep on the cluster, kill a worker, run it again; print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=334)
    parser.add_argument("--kill-at", type=float, default=0.3, help="share of runs in")
    parser.add_argument("--out", type=Path, help="results file (default: a temporary one)")
    args = parser.parse_args()
    cal = Calibration.measure()
    total = args.seeds * len(SHAPES) * len(ROBOTS)
    with tempfile.TemporaryDirectory(prefix="phalanx-sweep-") as folder:
        out = args.out or Path(folder) / "runs.jsonl"
        out.unlink(missing_ok=True)
        cluster = Cluster(Path(folder))
        try:
            address = cluster.scheduler()
            doomed = cluster.worker("w1")
            cluster.worker("w2")
            said = Path(folder) / "sweep.err"
            started = time.monotonic()
            with said.open("wb") as err:
                sweep = subprocess.Popen(
                    sweep_command(address, args.seeds, out), stdout=subprocess.DEVNULL,
                    stderr=err,
                )  # fmt: skip
            while len(result_keys(out)) < args.kill_at * total and sweep.poll() is None:
                time.sleep(0.5)
            before_kill = len(result_keys(out))
            killed_s = time.monotonic() - started
            cluster.kill(doomed)
            cluster.worker("w3")  # another host takes the lost one's place
            code = sweep.wait()
            wall_s = time.monotonic() - started
            done = result_keys(out)
            again_started = time.monotonic()
            again = subprocess.run(
                sweep_command(address, args.seeds, out), capture_output=True, text=True,
                check=False,
            )  # fmt: skip
            again_s = time.monotonic() - again_started
            added = len(result_keys(out)) - len(done)
            lines = progress_lines(said)
            lost = cluster.lost_results()
        finally:
            cluster.close()
        left = cluster.leftovers()
    print(f"sweep of {total} runs on 2 workers, exit code {code}: {wall_s / 60:.1f} min "
          f"({wall_s / total:.2f} s a run), {cal.cal(wall_s / total)} a run")  # fmt: skip
    print(f"worker killed at {killed_s / 60:.1f} min with {before_kill} runs in the file; "
          f"finished runs it took with it (done again): {len(lost)}")  # fmt: skip
    print(f"runs in the file: {len(done)} lines, {len(set(done))} different (want {total})")
    print(f"first estimate: {lines[0] if lines else '-'}")
    print(f"last progress: {lines[-1] if lines else '-'}")
    print(f"started again: exit code {again.returncode} in {again_s:.1f} s, "
          f"{added} runs added; it said: "
          f"{again.stderr.strip().splitlines()[-1] if again.stderr.strip() else '-'}")  # fmt: skip
    print(f"processes left: {left or 'none'}")


if __name__ == "__main__":
    main()
