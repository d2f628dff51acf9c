"""The processes a host daemon supervises: one `ManagedChild` per agent or world.

A child runs in its own session (process group), with its output piped to a reader
thread: every line is kept (the last error is what `status` shows) and handed, rate
limited, to the daemon's line sink. Stopping is SIGTERM to the whole group, then SIGKILL
after a grace period; a crashing child is restarted after an exponential back-off.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import IO, Literal

from phalanx.hosts.deployment import RestartPolicy
from phalanx.hosts.protocol import ACTIVE_STATES, MAX_LOG_LINE, ChildState, ChildStatus, line_level
from phalanx.runtime.exits import exit_reason
from phalanx.runtime.process_spec import AgentSpec, hand_spec
from phalanx.runtime.signals import supervised_env

LOG_LINES_PER_S = 200.0
__all__ = ["LogLevel", "ManagedChild", "backoff_delay_s", "exit_reason"]

LogLevel = Literal["info", "warning", "error"]
LineSink = Callable[["ManagedChild", str, LogLevel], None]


class ManagedChild:
    """One supervised process: its state, restarts, output and last error; an agent
    with its `spec`, written to its standard input at each start.
    """

    def __init__(
        self,
        name: str,
        kind: Literal["agent", "world"],
        argv: list[str],
        *,
        policy: RestartPolicy,
        on_line: LineSink,
        spec: AgentSpec | None = None,
    ) -> None:
        self.name, self.kind, self.argv, self.spec = name, kind, argv, spec
        self.policy = policy
        self.on_line = on_line
        self.process: subprocess.Popen[bytes] | None = None
        self.state: ChildState = "starting"
        self.restarts = 0
        self.crashes = 0
        self.backoff_steps = 0
        self.exit_code: int | None = None
        self.last_error = ""
        self.lines: deque[str] = deque(maxlen=50)
        self.log_dropped = 0
        self.started_at = 0.0
        self.restart_at = 0.0
        self.kill_at = 0.0
        self._tokens = LOG_LINES_PER_S
        self._refilled = time.monotonic()
        self._pump: threading.Thread | None = None

    @property
    def active(self) -> bool:
        """Running, starting, about to restart or being stopped."""
        return self.state in ACTIVE_STATES

    def start(self, *, workdir: Path) -> None:
        """Start (again), output piped to a reader thread."""
        env = {**supervised_env(), "PYTHONUNBUFFERED": "1"}
        self.process = subprocess.Popen(  # noqa: S603 - argv built from the deployment file
            self.argv,
            stdin=subprocess.DEVNULL if self.spec is None else subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            cwd=workdir,
            env=env,
            start_new_session=True,
        )
        if self.spec is not None:
            hand_spec(self.process, self.spec)
        self.state, self.exit_code = "starting", None
        self.started_at = time.monotonic()
        self._pump = threading.Thread(
            target=self._read, args=(self.process.stdout,), name=f"log-{self.name}", daemon=True
        )
        self._pump.start()

    def poll(self) -> int | None:
        """The exit code, if the process has ended."""
        return None if self.process is None else self.process.poll()

    def signal(self, sig: signal.Signals) -> None:
        """Signal the child's whole process group."""
        if self.process is not None and self.process.poll() is None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.process.pid, sig)

    def stop(self, now: float, grace_s: float) -> None:
        """SIGTERM now, SIGKILL after `grace_s`; a pending restart is cancelled."""
        if self.state in ("starting", "running"):
            self.signal(signal.SIGTERM)
            self.state, self.kill_at = "stopping", now + grace_s
        elif self.state == "backoff":
            self.state = "stopped"

    def join_output(self, timeout_s: float) -> None:
        """Wait (bounded) for the reader thread to see the end of the output."""
        if self._pump is not None:
            self._pump.join(timeout_s)

    def status(self) -> ChildStatus:
        """The child as the protocol reports it."""
        pid = self.process.pid if self.process is not None and self.active else None
        return ChildStatus(
            name=self.name,
            kind=self.kind,
            state=self.state,
            pid=pid,
            restarts=self.restarts,
            crashes=self.crashes,
            exit_code=self.exit_code,
            last_error=self.last_error[-300:],
            log_dropped=self.log_dropped,
        )

    def _read(self, stream: IO[bytes] | None) -> None:
        if stream is None:
            return
        with stream, contextlib.suppress(OSError, ValueError):  # closed at EOF
            for raw in stream:
                line = raw.decode("utf-8", "replace").rstrip()[:MAX_LOG_LINE]
                if line:
                    self._take(line)

    def _take(self, line: str) -> None:
        self.lines.append(line)
        level = line_level(line)
        if level == "error":
            self.last_error = line
        now = time.monotonic()
        self._tokens = min(LOG_LINES_PER_S, self._tokens + (now - self._refilled) * LOG_LINES_PER_S)
        self._refilled = now
        if self._tokens < 1.0:
            self.log_dropped += 1
            return
        self._tokens -= 1.0
        self.on_line(self, line, level)


def backoff_delay_s(policy: RestartPolicy, step: int) -> float:
    """The delay before restart number `step + 1` of a crashing child."""
    return float(min(policy.backoff_max_s, policy.backoff_s * 2.0**step))
