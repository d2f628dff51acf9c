"""Stopping long-running loops from SIGINT/SIGTERM without deadlocks.

Every process loop of phalanx (agent, world, host daemon, launcher) polls a `Stoppable`.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import time
from typing import Protocol

# Set by a supervisor (`phalanx up`, a host daemon) in its children's environment: the
# child stops (SIGTERM, handled like any) when that process dies, rather than run on as
# an orphan nobody supervises.
PARENT_ENV = "PHALANX_PARENT_PID"
_PR_SET_PDEATHSIG = 1


class Stoppable(Protocol):
    """What a long-running loop polls to know it must stop (threading.Event is one)."""

    def is_set(self) -> bool:
        """Whether stopping was asked for."""

    def wait(self, timeout: float | None = None) -> bool:
        """Sleep until asked to stop or `timeout` passes; whether it was asked."""


class SignalStop:
    """A stop flag for SIGINT/SIGTERM handlers: setting it takes no lock.

    `threading.Event.set` takes a lock, and a handler runs on the main thread between
    two bytecodes: a second signal arriving while a first handler is inside `set`
    deadlocks the process. Signals do come in bursts (a supervisor and systemd both
    sending SIGTERM; a parent-death signal is sent once per thread). Here `set` is one
    assignment and `wait` polls.
    """

    def __init__(self, poll_s: float = 0.02) -> None:
        self._asked = False
        self.poll_s = poll_s

    def set(self) -> None:
        """Ask to stop (safe in a signal handler)."""
        self._asked = True

    def is_set(self) -> bool:
        """Whether stopping was asked for."""
        return self._asked

    def wait(self, timeout: float | None = None) -> bool:
        """Sleep until asked to stop or `timeout` passes; whether it was asked."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._asked:
            left = self.poll_s if deadline is None else deadline - time.monotonic()
            if left <= 0.0:
                break
            time.sleep(min(self.poll_s, left))
        return self._asked


def stop_on_signals() -> SignalStop:
    """A SignalStop set by SIGINT or SIGTERM (any number of them, in any burst)."""
    stop = SignalStop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def supervised_env() -> dict[str, str]:
    """The environment for a supervised child: this process is its parent."""
    return {**os.environ, PARENT_ENV: str(os.getpid())}


def die_with_parent() -> None:
    """If a supervisor started this process (`PARENT_ENV`), have the kernel send it
    SIGTERM when that supervisor dies (Linux; elsewhere nothing), and stop at once if it
    is already gone.
    """
    parent = os.environ.get(PARENT_ENV)
    if not parent or not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        return
    if str(os.getppid()) != parent:  # it died before the prctl took effect
        os.kill(os.getpid(), signal.SIGTERM)
