"""The commands that run processes follow the results-folder rule and talk: `phalanx up`
takes `results/<scenario>-<controller>-up`, or `-up-2` beside an earlier run, and says
so; `phalanx launch` reports the world's progress on stderr (a line every tenth of the
run in a pipe) and ends naming the run's folder on the world's host, named after the
deployment."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest
from fleetlab import CLI, WEDGE, deployment_file

pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.timeout(180)]


def test_up_writes_beside_an_earlier_run_and_says_where(tmp_path: Path) -> None:
    earlier = tmp_path / "results" / "paper-wedge-ours-up"
    earlier.mkdir(parents=True)
    (earlier / "metrics.json").write_text('{"earlier": true}')
    done = subprocess.run(
        [*CLI, "up", str(WEDGE), "--set", "duration_s=2", "--no-recording", "--fleet",
         "outputs-up", "--timeout", "120"],
        capture_output=True, text=True, timeout=150, cwd=tmp_path, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.splitlines()[-1] == "results: results/paper-wedge-ours-up-2"
    assert done.stdout.count("results: ") == 1, done.stdout  # (the world's child says none)
    assert (earlier / "metrics.json").read_text() == '{"earlier": true}'
    assert (tmp_path / "results" / "paper-wedge-ours-up-2" / "metrics.json").is_file()
    assert re.search(r"^up: 2 of 2 s of run \(100 %\), .* done$", done.stderr, re.MULTILINE)


def test_launch_reports_its_progress_and_names_the_results_folder(tmp_path: Path) -> None:
    path, _ = deployment_file(tmp_path, name="talks", duration_s=6.0, recording=False)
    done = subprocess.run(
        [*CLI, "launch", str(path), "--local", "--no-table", "--no-logs", "--host-wait", "60"],
        capture_output=True, text=True, timeout=150, cwd=tmp_path, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    progress = [line for line in done.stderr.splitlines() if line.startswith("launch: ")]
    assert progress, done.stderr
    assert 2 <= len(progress) <= 13  # a pipe: every tenth of the run (or 30 s), and the end
    assert re.fullmatch(r"launch: 6 of 6 s of run \(100 %\), .* done", progress[-1])
    assert any("left" in line for line in progress)
    said = done.stdout.splitlines()[-1]
    found = re.search(r"results on host laptop: (.+)$", said)
    assert found is not None, done.stdout[-2000:]
    folder = Path(found.group(1))
    assert folder.parent == tmp_path / "results"
    assert re.fullmatch(r"talks-\d{8}-\d{6}-[0-9a-f]{4}", folder.name)
    assert (folder / "metrics.json").is_file()


def test_launch_quiet_says_no_progress(tmp_path: Path) -> None:
    path, _ = deployment_file(tmp_path, name="hush", duration_s=2.0, recording=False)
    done = subprocess.run(
        [*CLI, "launch", str(path), "--local", "--no-table", "--no-logs", "--quiet",
         "--host-wait", "60"],
        capture_output=True, text=True, timeout=150, cwd=tmp_path, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert "launch: " not in done.stderr
    assert "results on host laptop: " in done.stdout


# In every `phalanx host` started with it on PYTHONPATH: 8 s asleep before it runs, as a
# daemon starts on a slow or busy machine (a launcher that waited 5 s gave up on it).
_SLOW_DAEMON = """
import time
from pathlib import Path

if b"\\0host\\0" in Path("/proc/self/cmdline").read_bytes():
    time.sleep(8.0)
"""


def test_launch_local_waits_for_its_daemons_as_long_as_host_wait(tmp_path: Path) -> None:
    path, _ = deployment_file(tmp_path, name="slow", duration_s=2.0, recording=False)
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(_SLOW_DAEMON)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")])),
    }
    done = subprocess.run(
        [*CLI, "launch", str(path), "--local", "--no-table", "--no-logs", "--host-wait", "60"],
        capture_output=True, text=True, timeout=150, cwd=tmp_path, env=env, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert "results on host laptop: " in done.stdout.splitlines()[-1], done.stdout[-2000:]
