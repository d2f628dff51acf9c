"""How a fleet process says why it ended: its exit code, and the words for one.

A supervisor (`phalanx up`, a host daemon) takes 0 for a finished run and anything else
for an ending that was not asked for: it reports it (and restarts an agent).

The same codes end `phalanx world`, `up` and `launch`: 0 only for a run complete by its
own metrics (`complete` in `metrics.json`); 1 when a process of it died or it was stopped
(timeout, Ctrl-C); 5 when every process ended as asked but the results say the run is
incomplete (a robot out of the world's sight, a report that never came, ticks not run);
6 when the results could not be written in full (a full disk). Each says why.
"""

from __future__ import annotations

import contextlib
import signal

EXIT_FINISHED = 0  # the run reached its end
EXIT_FAILED = 1  # an error ended it
EXIT_USAGE = 2  # what the user gave is wrong (a file, a value), or the robot was unreachable
EXIT_WORLD_LOST = 3  # an agent on the sim driver heard no frame from the world for too long
EXIT_RUN_CUT_SHORT = 4  # an agent's world ended the run before its last tick
EXIT_INCOMPLETE = 5  # the run ended, but its results say it is incomplete
EXIT_RESULTS_LOST = 6  # the results could not be written in full (a full disk)

_MEANINGS = {
    EXIT_WORLD_LOST: "no frame from the world for --frame-timeout",
    EXIT_RUN_CUT_SHORT: "the world ended the run before its last tick",
    EXIT_INCOMPLETE: "the run is incomplete by its own metrics",
    EXIT_RESULTS_LOST: "its results could not be written in full",
}


def exit_reason(code: int) -> str:
    """`exit 2`, or `killed by SIGKILL` for a negative code."""
    if code < 0:
        with contextlib.suppress(ValueError):
            return f"killed by {signal.Signals(-code).name}"
        return f"killed by signal {-code}"
    return f"exit {code}"


def agent_exit_reason(code: int) -> str:
    """A phalanx process's exit code in words: `exit 4 (the world ended the run ...)`."""
    meaning = _MEANINGS.get(code)
    return f"{exit_reason(code)} ({meaning})" if meaning else exit_reason(code)
