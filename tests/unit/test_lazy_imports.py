"""The command line imports only what a command needs. Importing it and `phalanx --help`
load none of the heavy libraries, a verb's `--help` none but pydantic (typer's), and a run
without figures or recording neither matplotlib nor Rerun. This checks what is
imported, not how long it takes (`bench/bench_startup.py` times it). Each check runs in a
fresh interpreter, so nothing this test process has imported counts.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from heavy_imports import HEAVY, WORK_LIBRARIES

REPO = Path(__file__).resolve().parents[2]
WEDGE = REPO / "configs" / "scenarios" / "paper_wedge.toml"
# A fresh interpreter runs `work`, then prints the heavy libraries it has loaded.
PROBE = """
import json, sys
{work}
loaded = sorted({{name.partition(".")[0] for name in sys.modules}} & set({heavy!r}))
print("\\nloaded:", json.dumps(loaded))
"""


def _loaded(work: str) -> list[str]:
    """The heavy libraries a fresh interpreter has loaded after running `work`."""
    code = PROBE.format(work=work, heavy=HEAVY)
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )
    assert done.returncode == 0, done.stderr[-3000:]
    last = done.stdout.rstrip().splitlines()[-1]
    assert last.startswith("loaded: "), done.stdout[-2000:]
    found: list[str] = json.loads(last.removeprefix("loaded: "))
    return found


def _cli(*args: str) -> str:
    """Code that runs `phalanx ARGS` as the console script does, its exit caught."""
    return (
        f"sys.argv = ['phalanx', *{list(args)!r}]\n"
        "from phalanx.cli import main\n"
        "try:\n    main()\nexcept SystemExit as done:\n    assert not done.code, done.code\n"
    )


def test_importing_the_command_line_loads_no_heavy_library() -> None:
    assert _loaded("import phalanx.cli") == []


def test_the_top_level_help_loads_no_heavy_library() -> None:
    assert _loaded(_cli("--help")) == []


def test_no_verbs_help_loads_a_library_its_work_needs_nor_numpy() -> None:
    # (typer turns each option's value through pydantic: any verb's help loads that)
    work = (
        "from typer.testing import CliRunner\n"
        "from phalanx.cli import app\n"
        "infos = [*app.registered_commands, *app.registered_groups]\n"
        "verbs = [info.name for info in infos]\n"
        "assert len(verbs) >= 20, verbs\n"
        "for verb in verbs:\n"
        "    result = CliRunner().invoke(app, [verb, '--help'])\n"
        "    assert result.exit_code == 0, (verb, result.output)\n"
    )
    assert set(_loaded(work)) <= {"pydantic"}


def test_a_run_without_figures_or_recording_loads_neither_matplotlib_nor_rerun(
    tmp_path: Path,
) -> None:
    run = _cli(
        "run", str(WEDGE), "--set", "duration_s=1", "--no-figures", "--no-recording",
        "--out", str(tmp_path / "run"),
    )  # fmt: skip
    loaded = _loaded(run)
    assert "numpy" in loaded  # (it did run)
    assert (tmp_path / "run" / "metrics.json").exists()
    assert set(loaded) & set(WORK_LIBRARIES) == set()
