"""Progress of a long command on stderr, with an estimate of the time left.

In a terminal (stderr a TTY): one line rewritten in place (a carriage return). In a pipe or a CI
log: a line every tenth of the work or every 30 s, whichever comes first, and the last
one, so a log of 1000 updates holds about a dozen lines. stdout (the tables) is left alone.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

PIPE_STEP = 0.1  # a pipe's line every tenth of the work ...
PIPE_PERIOD_S = 30.0  # ... or every 30 s
TTY_PERIOD_S = 0.2  # a terminal's line rewritten at most this often


def duration(seconds: float) -> str:
    """A short human duration: "45 s", "3 min", "1 h 35 min" ("?" if unknown)."""
    if not math.isfinite(seconds) or seconds < 0:
        return "?"
    if seconds < 60:
        return f"{seconds:.0f} s"
    minutes = round(seconds / 60)
    if minutes < 60:
        return f"{minutes} min"
    return f"{minutes // 60} h {minutes % 60:02d} min"


def time_left(done: float, total: float, elapsed_s: float) -> float:
    """The time left by the mean rate so far (NaN before any work is done)."""
    if done <= 0 or total <= 0 or elapsed_s <= 0:
        return math.nan
    return max(0.0, elapsed_s * (total - done) / done)


def progress_line(
    label: str,
    done: float,
    total: float,
    elapsed_s: float,
    *,
    unit: str = "",
    left_s: float | None = None,
) -> str:
    """One progress line: "sweep: 12 of 300 runs (4 %), 2 min elapsed, about 48 min left".
    The time left is `left_s` (NaN: none said yet), or by the mean rate since the start.
    """
    total = max(total, 0.0)
    done = min(max(done, 0.0), total) if total else max(done, 0.0)
    pct = f" ({100 * done / total:.0f} %)" if total else ""
    count = f"{done:.0f} of {total:.0f}{' ' + unit if unit else ''}{pct}"
    line = f"{label}: {count}, {duration(elapsed_s)} elapsed"
    if total and done >= total:
        return line + ", done"
    left = time_left(done, total, elapsed_s) if left_s is None else left_s
    return line + (f", about {duration(left)} left" if math.isfinite(left) else "")


def sweep_statement(runs: int, per_run_s: float, workers: int) -> str:
    """What a sweep says before it starts: "300 runs, about 95 min on 2 workers"."""
    workers = max(workers, 1)
    if runs <= 0:
        return "0 runs to do (every run is in the results file already)"
    waves = math.ceil(runs / workers)
    noun = "run" if runs == 1 else "runs"
    per = "worker" if workers == 1 else "workers"
    return f"{runs} {noun}, about {duration(waves * per_run_s)} on {workers} {per}"


class Stream(Protocol):
    """Where progress lines go: stderr, or anything that takes text the same way."""

    def write(self, text: str, /) -> int:
        """Write `text`; the characters written."""
        ...

    def flush(self) -> None:
        """Push what was written out."""
        ...


@dataclass
class Reporter:
    """Writes progress lines to `stream` (stderr by default): in place on a TTY, sparse
    in a pipe. Call it with (done, total); `close` ends the line.

    `from_first`: the time left by the rate since the first report, not since the
    reporter was made (work that runs at its own pace once it starts, such as a run's
    clock after its processes have started: start-up time says nothing of what is left).
    """

    label: str
    unit: str = ""
    stream: Stream | None = None
    quiet: bool = False
    tty: bool | None = None  # (None: whether `stream` is a terminal)
    clock: Callable[[], float] | None = None  # (seconds; None: time.monotonic)
    from_first: bool = False
    _start: float = field(default=math.nan, init=False)
    _first: tuple[float, float] | None = field(default=None, init=False)  # (time, done)
    _last_fraction: float = field(default=-1.0, init=False)
    _last_time: float = field(default=-math.inf, init=False)
    _last_line: str = field(default="", init=False)
    _open: bool = field(default=False, init=False)

    def __post_init__(self) -> None:
        if self.stream is None:
            self.stream = sys.stderr
        if self.tty is None:
            isatty = getattr(self.stream, "isatty", None)
            self.tty = bool(isatty()) if callable(isatty) else False
        self._start = self._now()

    def _now(self) -> float:
        return self.clock() if self.clock is not None else time.monotonic()

    def __call__(self, done: float, total: float) -> None:
        """Report `done` of `total` (each line, or a pipe's next when due)."""
        if self.quiet or self.stream is None:
            return
        now = self._now()
        line = progress_line(
            self.label,
            done,
            total,
            now - self._start,
            unit=self.unit,
            left_s=self._left(now, done, total),
        )
        if self.tty:
            if now - self._last_time < TTY_PERIOD_S and not (total > 0 and done >= total):
                return
            self.stream.write("\r" + line.ljust(len(self._last_line)))
            self._open, self._last_time = True, now
        else:
            fraction = done / total if total > 0 else 0.0
            finished = total > 0 and done >= total
            due = fraction - self._last_fraction >= PIPE_STEP or now - self._last_time >= (
                PIPE_PERIOD_S
            )
            if not (due or (finished and self._last_fraction < 1.0)):
                return
            self.stream.write(line + "\n")
            self._last_fraction, self._last_time = fraction, now
        self._last_line = line
        self.stream.flush()

    def _left(self, now: float, done: float, total: float) -> float | None:
        """The time left `from_first` (None: by the mean since the start)."""
        if not self.from_first:
            return None
        if self._first is None:
            self._first = (now, done)
        since, before = self._first
        return time_left(done - before, total - before, now - since)

    def say(self, text: str) -> None:
        """A line of its own (such as a sweep's statement before it starts)."""
        if self.quiet or self.stream is None:
            return
        self.close()
        self.stream.write(text + "\n")
        self.stream.flush()

    def close(self) -> None:
        """End the in-place line (a TTY's), so what follows starts on a line of its own."""
        if self._open and self.stream is not None:
            self.stream.write("\n")
            self.stream.flush()
            self._open = False
