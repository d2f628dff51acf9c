"""Stopping long-running loops from SIGINT/SIGTERM without deadlocks.

Every process loop of phalanx (agent, world, host daemon, launcher) polls a `Stoppable`.
"""

from __future__ import annotations

import signal
import time
from typing import Protocol


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
