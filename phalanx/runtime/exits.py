"""How a fleet process says why it ended: its exit code, and the words for one.

A supervisor (`phalanx up`, a host daemon) takes 0 for a finished run and anything else
for an ending that was not asked for: it reports it (and restarts an agent).
"""

from __future__ import annotations

import contextlib
import signal

EXIT_FINISHED = 0  # the run reached its end
EXIT_FAILED = 1  # an error ended it
EXIT_USAGE = 2  # what the user gave is wrong (a file, a value), or the robot was unreachable
EXIT_WORLD_LOST = 3  # an agent on the sim driver heard no frame from the world for too long
EXIT_RUN_CUT_SHORT = 4  # an agent's world ended the run before its last tick

_MEANINGS = {
    EXIT_WORLD_LOST: "no frame from the world for --frame-timeout",
    EXIT_RUN_CUT_SHORT: "the world ended the run before its last tick",
}


def exit_reason(code: int) -> str:
    """`exit 2`, or `killed by SIGKILL` for a negative code."""
    if code < 0:
        with contextlib.suppress(ValueError):
            return f"killed by {signal.Signals(-code).name}"
        return f"killed by signal {-code}"
    return f"exit {code}"


def agent_exit_reason(code: int) -> str:
    """An agent's exit code in words: `exit 4 (the world ended the run ...)`."""
    meaning = _MEANINGS.get(code)
    return f"{exit_reason(code)} ({meaning})" if meaning else exit_reason(code)
