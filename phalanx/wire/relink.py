"""Re-opening a session that has gone deaf.

Zenoh clients come back by themselves when their router comes back, except (1.10, on
the low-latency transport; measured in `bench/bench_relink.py`) sometimes after the
router stopped past the lease (a frozen process, a stalled host): the client is attached
again, but the router has dropped what it had declared. The
client looks connected and hears nothing, for good; the rest of the fleet no longer sees
its liveliness. Zenoh cannot tell it; only its owner can, by what stops arriving (an
agent: the world's frames, its peers' flags).

`Relinker` watches that: when what its owner expects to hear has been silent for
`after_s`, it re-opens the session (`FleetSession.relink`), then waits twice as long
before the next attempt while the silence lasts (a world that ended, a fleet that is
gone: the attempts thin out to one every `max_after_s`). Hearing again resets the wait.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from phalanx.core.lifecycle import Closing
from phalanx.wire.transport import FleetSession

log = logging.getLogger("phalanx.transport")

# Past the Zenoh lease (1 s), a reconnection of Zenoh's own (its retries, at most 1 s
# apart on a deployment's sessions), and more than twice the longest a running world
# waits between two frames (its tick timeout, 2 s): a link coming back has by then.
RELINK_AFTER_S = 5.0
RELINK_MAX_AFTER_S = 30.0
POLL_S = 0.25
STALLED_S = 1.0  # a poll this late: the process itself was frozen (not its link)
Heard = Callable[[], float | None]  # when the owner last heard what it expects (monotonic)


class Relinker(Closing):
    """Re-opens `session` whenever `heard` has been silent for a while (module docstring).

    `heard()` gives the monotonic time at which the owner last heard what it expects,
    or None while it expects nothing (a lone robot: no silence is suspect). A session
    that cannot relink (a router's, listening) is left alone. `check` takes one
    decision; `start` runs it every `POLL_S` on a thread of its own, which `close` ends
    (a relink under way finishes first, within its open timeout).
    """

    def __init__(
        self,
        session: FleetSession,
        heard: Heard,
        *,
        after_s: float = RELINK_AFTER_S,
        max_after_s: float = RELINK_MAX_AFTER_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.session = session
        self.heard = heard
        self.after_s, self.max_after_s = after_s, max(after_s, max_after_s)
        self._clock = clock
        self._wait_s = after_s
        self._since = clock()  # silence is counted from the latest of this and `heard()`
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def check(self) -> bool:
        """Relink if the silence has lasted the current wait; whether it relinked."""
        heard, now = self.heard(), self._clock()
        if heard is None or not self.session.can_relink:
            self._since = now
            return False
        if heard > self._since:
            self._since, self._wait_s = heard, self.after_s
        if now - self._since < self._wait_s:
            return False
        log.warning("nothing heard for %.1f s: re-opening the Zenoh session", now - heard)
        relinked = self.session.relink()
        self._since = self._clock()
        self._wait_s = min(self.max_after_s, 2 * self._wait_s)
        return relinked

    def start(self) -> None:
        """Check every `POLL_S` until `close`."""
        self._thread = threading.Thread(target=self._run, name="relinker", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        woke = self._clock()
        while not self._stop.wait(POLL_S):
            # A wake-up this late means this process was stopped or starved: what arrived
            # meanwhile is still on its way in. Decide on the next one.
            late = self._clock() - woke > STALLED_S
            woke = self._clock()
            try:
                if not late:
                    self.check()
            except Exception:  # a failed relink must not end the watch, nor the process
                log.exception("re-opening the Zenoh session failed")

    def close(self) -> None:
        """Stop watching; safe twice."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
