"""Which of the world's sense frames a simulated robot acts on.

The frames are the robot's readings and its clock, so a frame that is not the world's,
or not the newest, would move the robot's time: a leader resumed after a freeze would
step through every frame it missed (publishing stale states as the leader it no longer
is), and a frame stamped far ahead would make every other robot look silent. The gate:

- takes the newest frame waiting (the others are stale: skipped, counted);
- drops a frame no newer than the last one acted on;
- holds a frame that jumps more than `max_jump` ticks ahead until the next tick confirms
  it (a world that really moved on sends tick + 1; a lone forged frame never is);
- ends the run on a final frame at the run's last tick; one far ahead of the last frame
  acted on (the robot missed the run's last ticks), or one before the last tick, ends it
  only once no frame has followed it for `confirm_s` (a world still running sends the
  next one within its tick timeout), and the one before the last tick as cut short, not
  finished.

Every frame refused is counted in the session's `DecodeStats` (`rejected`).
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from phalanx.wire.codec import DecodeStats
from phalanx.wire.messages import SenseFrame

FRAME_RING = 64  # frames held between two steps (one arrives per period)
# Longer than the world's tick timeout (2 s): a world still running sends a frame within.
FINAL_CONFIRM_S = 3.0
MAX_JUMP_S = 1.0  # a frame this far ahead of the last one needs the next to confirm it
Ending = Literal["finished", "cut_short"]
_KIND = "SenseFrame"


@dataclass
class FrameCounts:
    """What the gate did with the frames it got."""

    acted: int = 0
    skipped: int = 0  # older than a newer frame waiting with it (the robot was late)


class FrameBox:
    """The frames arrived and not yet taken: a bounded ring (the oldest dropped and
    counted when full), filled on Zenoh's thread, emptied by the agent's loop.
    """

    def __init__(self, stats: DecodeStats, capacity: int = FRAME_RING) -> None:
        self._stats = stats
        self._frames: deque[SenseFrame] = deque(maxlen=capacity)
        self._arrived = threading.Condition()
        self.put_s: float | None = None  # when the last frame came (monotonic)

    def put(self, frame: SenseFrame) -> None:
        """A decoded frame (Zenoh's thread)."""
        with self._arrived:
            self.put_s = time.monotonic()
            if len(self._frames) == self._frames.maxlen:
                self._stats.ring_dropped[_KIND] += 1
            self._frames.append(frame)
            self._arrived.notify()

    def newest_tick(self) -> int | None:
        """The newest tick waiting (None: nothing waits)."""
        with self._arrived:
            return max((f.tick for f in self._frames if not f.final), default=None)

    def take(self, timeout_s: float) -> list[SenseFrame]:
        """Every frame waiting, oldest first; waits up to `timeout_s` for one."""
        with self._arrived:
            if not self._frames:
                self._arrived.wait(timeout_s)
            frames = list(self._frames)
            self._frames.clear()
        return frames


class FrameGate:
    """Decides, frame by frame, which the robot acts on (see the module docstring)."""

    def __init__(
        self,
        stats: DecodeStats,
        *,
        last_tick: int | None,
        dt_s: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.stats = stats
        self.last_tick = last_tick  # the run's final tick (None: unknown, any final ends it)
        self.max_jump = max(2, math.ceil(MAX_JUMP_S / dt_s))
        self.counts = FrameCounts()
        self.ending: Ending | None = None
        self._clock = clock
        self._tick: int | None = None
        self._suspect: SenseFrame | None = None
        self._final: tuple[SenseFrame, float] | None = None

    def offer(self, frames: list[SenseFrame]) -> SenseFrame | None:
        """The frame to act on among `frames` (oldest first), if any."""
        chosen = None
        for frame in frames:
            if frame.final:
                self._offer_final(frame)
            elif self._plausible(frame):
                if chosen is not None:
                    self.counts.skipped += 1
                chosen = frame
        if chosen is not None:
            self._refute_final()
            self._tick = chosen.tick
            self.counts.acted += 1
        return chosen

    def ended(self) -> bool:
        """Whether the run is over: a final frame at its end, or one never refuted."""
        if self._final is not None and self._clock() - self._final[1] > FINAL_CONFIRM_S:
            # (at the run's last tick: the run did end there, this robot missed its last
            # ticks, frozen or cut off; the world's log says so)
            self.ending = "finished" if self._at_end(self._final[0]) else "cut_short"
        return self.ending is not None

    def _plausible(self, frame: SenseFrame) -> bool:
        last = self._tick
        suspect, self._suspect = self._suspect, None
        if last is None or last < frame.tick <= last + self.max_jump:
            self._refuse_jump(suspect, last)
            return True
        if frame.tick <= last:
            self._suspect = suspect
            self._refuse(frame, f"tick {frame.tick} is not after {last}")
            return False
        if suspect is not None and frame.tick == suspect.tick + 1:
            return True  # the world really moved on: the next tick confirms the jump
        self._refuse_jump(suspect, last)
        self._suspect = frame
        return False

    def _refuse_jump(self, suspect: SenseFrame | None, last: int | None) -> None:
        if suspect is not None:
            self._refuse(suspect, f"tick {suspect.tick} jumped from {last}, never confirmed")

    def _offer_final(self, frame: SenseFrame) -> None:
        last = self._tick
        near = last is None or last - 1 <= frame.tick <= last + self.max_jump
        if near and self._at_end(frame):
            self.ending = "finished"
        elif self._final is None:
            self._final = (frame, self._clock())

    def _at_end(self, frame: SenseFrame) -> bool:
        return self.last_tick is None or frame.tick >= self.last_tick

    def _refute_final(self) -> None:
        if self._final is not None:
            frame = self._final[0]
            self._refuse(frame, f"final frame at tick {frame.tick}, but the world went on")
            self._final = None

    def _refuse(self, frame: SenseFrame, why: str) -> None:
        self.stats.count("rejected", _KIND, f"{_KIND} of {frame.robot_id}: {why}")
