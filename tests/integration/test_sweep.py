"""`phalanx sweep` on a local Dask cluster of two worker processes: the same numbers as
the runs made in this process, finished runs never run again, one table."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from phalanx.analysis.sweep import (
    QUIET_DASK,
    done_rows,
    jobs,
    read_rows,
    run_job,
    summaries,
    table,
)
from phalanx.core.errors import ConfigError

pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.timeout(240)]

SHORT = (("duration_s", 12.0),)


def _sweep(out: Path, seeds: int) -> str:
    # (in a process of its own: Dask's local cluster leaves a multiprocessing helper
    # running in the process that made it, until that process ends)
    done = subprocess.run(
        [str(Path(sys.executable).parent / "phalanx"), "sweep", "--seeds", str(seeds), "--shape",
         "inline", "--workers", "2", "--out", str(out), "--set", "duration_s=12.0"],
        capture_output=True, text=True, timeout=200, check=True,
    )  # fmt: skip
    return done.stdout


def test_a_sweep_on_two_local_workers_is_resumable_and_matches_in_process(tmp_path: Path) -> None:
    out = tmp_path / "runs.jsonl"
    _sweep(out, 1)
    first = out.read_text(encoding="utf-8").splitlines()
    printed = _sweep(out, 2)  # seed 0 is not run again
    lines = out.read_text(encoding="utf-8").splitlines()
    assert len(lines) == 2
    assert lines[0] == first[0]
    # a pipe: 80 columns, the 19 columns as a block of `field: value` lines, no pipes
    assert re.search(r"^formation: +inline$", printed, re.MULTILINE), printed
    assert re.search(r"^runs: +2$", printed, re.MULTILINE), printed
    assert "|" not in printed
    *shown, said = printed.splitlines()
    assert max(len(line) for line in shown) <= 80
    assert said.endswith(f"results: {out}")
    rows = done_rows(out)
    todo = jobs(["field"], ["inline"], [3], [0, 1], overrides=SHORT)
    assert set(rows) == {j.key for j in todo}
    local = run_job(todo[1])
    for key in ("goal_reached", "collisions_obstacle", "episode_share", "calm", "route_s"):
        assert json.loads(json.dumps(local[key])) == rows[todo[1].key][key]
    _sweep(out, 2)
    assert out.read_text(encoding="utf-8").splitlines() == lines
    assert "| field | inline | 3 | ours | 2 |" in "\n".join(table(summaries(list(rows.values()))))


def test_a_line_that_holds_no_run_is_left_out_and_its_run_done_again(tmp_path: Path) -> None:
    row = run_job(jobs(["field"], ["inline"], [3], [0], overrides=SHORT)[0])
    good = json.dumps(row, allow_nan=True)
    spoilt = {**row, "time_to_goal_s": "x", "goal_reached": "banana"}
    out = tmp_path / "runs.jsonl"
    # a run's record; one with its key but not its fields (the summary once ended in a
    # traceback on it); a line of another kind; a torn last line
    lines = [good, json.dumps(spoilt), '{"key": "a", "x": 1}', good[:40]]
    out.write_text("\n".join(lines), encoding="utf-8")
    rows, skipped = read_rows(out)
    assert list(rows) == [row["key"]]
    assert json.dumps(rows[row["key"]], allow_nan=True) == good  # (NaN is no NaN's equal)
    assert skipped == 3
    assert list(done_rows(out)) == [row["key"]]
    out.write_bytes(b"\xff\xfe garbage")
    with pytest.raises(ConfigError, match="cannot read the results file"):
        read_rows(out)


def test_the_local_workers_keep_glibcs_trim_threshold_and_rarer_housekeeping() -> None:
    # Dask's nanny gives its workers MALLOC_TRIM_THRESHOLD_=65536 (freed memory back to
    # the system at once): a sweep's runs then fault their pages in afresh every step.
    # The sweep's own cluster drops that one setting and keeps the nanny's others, and
    # its workers run Dask's housekeeping as rarely as QUIET_DASK says.
    probe = (
        "import json, os, dask\n"
        "from dask.distributed import Client\n"
        "from phalanx.analysis.sweep import QUIET_DASK, local_cluster\n"
        "with local_cluster(1) as cluster, Client(cluster) as client:\n"
        "    seen = client.run(lambda: ({k: os.environ.get(k) for k in "
        "('MALLOC_TRIM_THRESHOLD_', 'OMP_NUM_THREADS')}, "
        "{k: dask.config.get(k) for k in QUIET_DASK}))\n"
        "print(json.dumps(list(seen.values())))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True
    )
    ((environ, housekeeping),) = json.loads(done.stdout.strip().splitlines()[-1])
    assert environ == {"MALLOC_TRIM_THRESHOLD_": None, "OMP_NUM_THREADS": "1"}
    assert housekeeping == QUIET_DASK
