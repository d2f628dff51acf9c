"""Where a command writes its results: one naming rule, and no silent overwrite.

The rule: a run of one scenario writes `results/<scenario>-<controller>`, and a command
other than `phalanx run` adds its name (`-up`, `-world`); the commands that run many
scenarios write a folder of their own under `results/` (`results/report`,
`results/sweep/runs.jsonl`); `phalanx launch` records on the world's host, under its
deployment's `[world] out_dir` (`results/deployments`), in a folder named after the run
(`<deployment>-<date>-<time>-<4 hex digits>` unless `--run-id` names it).

A folder that holds anything is never written into silently: the command takes the first
free `<folder>-2`, `<folder>-3`, ... instead, or, with `--force`, writes into the folder
named (its files of the same names replaced, the others left). Every command ends by
saying which folder it wrote.
"""

from __future__ import annotations

import secrets
import time
from pathlib import Path
from typing import Annotated

import typer

RESULTS_ROOT = Path("results")
MAX_SUFFIX = 10_000  # `<folder>-N` tried up to this N
# A launch's run id (at most 40 characters): the deployment's name cut to this, the time
# and 4 random hex digits (two launches in one second are two runs).
RUN_ID_NAME_CHARS = 19

ForceOpt = Annotated[
    bool,
    typer.Option(
        "--force",
        help="Write into the results folder even if it holds an earlier run (its files of "
        "the same names replaced); without it such a folder gets a numbered suffix, -2, -3.",
    ),
]


def results_name(scenario: str, controller: str, command: str = "run") -> Path:
    """The folder a run of `scenario` with `controller` by `command` is named by the rule:
    `results/<scenario>-<controller>`, with `-<command>` after it for any command but run.
    """
    suffix = "" if command == "run" else f"-{command}"
    return RESULTS_ROOT / f"{scenario}-{controller}{suffix}"


def holds_anything(folder: Path) -> bool:
    """Whether `folder` is there and not an empty folder (a file by that name counts)."""
    if not folder.exists():
        return False
    return not folder.is_dir() or any(folder.iterdir())


def fresh_folder(folder: Path, *, force: bool = False) -> Path:
    """`folder` if it is new or empty (or `force`); else the first free `<folder>-N`,
    N from 2. The folder returned is made here, so that two runs started at the same time
    do not both take it. A folder that cannot be made raises `ResultsNotWritten`.
    """
    if force:
        return folder
    for n in range(1, MAX_SUFFIX + 1):
        candidate = folder if n == 1 else folder.with_name(f"{folder.name}-{n}")
        try:
            candidate.mkdir(parents=True)
        except FileExistsError:
            if candidate.is_dir() and not holds_anything(candidate):
                return candidate
            continue
        except OSError as exc:
            raise _not_made(candidate, exc) from exc
        return candidate
    raise _not_made(folder, FileExistsError(17, f"-2 ... -{MAX_SUFFIX} are all taken"))


def _not_made(folder: Path, exc: OSError) -> Exception:
    """The error of a results folder that could not be made (matplotlib, which the
    results module loads, only imported then).
    """
    from phalanx.analysis.results import ResultsNotWritten

    return ResultsNotWritten(folder, "the results folder", exc)


def launch_run_id(deployment: str, *, now_s: float | None = None) -> str:
    """The name of a launch's run when --run-id gives none: the deployment's name (cut
    to `RUN_ID_NAME_CHARS`), the local date and time and 4 random hex digits,
    `loopback-20261201-142501-3fa2`; its results go to `<out_dir>/<run id>` on the
    world's host.
    """
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now_s))
    return f"{deployment[:RUN_ID_NAME_CHARS]}-{stamp}-{secrets.token_hex(2)}"
