"""What arrives on a fleet session, on its way to the code that owns it: decoded totally
and checked (`deliver`), or held raw in a bounded ring until its owner drains it
(`Polled`), and the last few values per robot (`History`). Every payload is either handed
on or counted in the session's `DecodeStats`.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from typing import Any, Generic, TypeVar

from phalanx.wire.codec import DecodeStats, decode
from phalanx.wire.keys import robot_of
from phalanx.wire.messages import Message

log = logging.getLogger("phalanx.transport")
M = TypeVar("M", bound=Message)


class History:
    """The last few decoded values per robot (thread-safe: a callback may fill it)."""

    def __init__(self, depth: int = 8) -> None:
        self._lock = threading.Lock()
        self._values: dict[str, deque[Any]] = {}
        self._depth = depth

    def push(self, robot_id: str, value: Any) -> None:
        """Add a value."""
        with self._lock:
            self._values.setdefault(robot_id, deque(maxlen=self._depth)).append(value)

    def values(self, robot_id: str) -> list[Any]:
        """A copy of the values held for `robot_id`, oldest first."""
        with self._lock:
            return list(self._values.get(robot_id, ()))

    def forget(self, robot_id: str) -> None:
        """Drop everything held for `robot_id`."""
        with self._lock:
            self._values.pop(robot_id, None)


class Polled(Generic[M]):
    """A subscription whose payloads wait in a ring of `capacity` until `drain` (see
    `FleetSession.subscribe_polled`). Zenoh's callback only appends the raw payload (no
    decoding on its thread); when the ring is full the oldest payload is dropped and
    counted (`DecodeStats.ring_dropped`).
    """

    def __init__(
        self, model: type[M], stats: DecodeStats, capacity: int, context: Any = None
    ) -> None:
        self._model = model
        self._stats = stats
        self._context = context
        self._ring: deque[tuple[str, bytes]] = deque(maxlen=capacity)
        self._lock = threading.Lock()

    def put(self, sample: Any) -> None:
        """Zenoh's side: keep the sample's key and payload (the oldest goes if full)."""
        item = (str(sample.key_expr), sample.payload.to_bytes())
        with self._lock:
            if len(self._ring) == self._ring.maxlen:
                self._stats.ring_dropped[self._model.__name__] += 1
            self._ring.append(item)

    def drain(self, on_message: Callable[[str, M], None]) -> int:
        """Call `on_message(key, value)` for every valid message waiting (the rest
        counted); how many payloads were taken.
        """
        with self._lock:
            items = list(self._ring)
            self._ring.clear()
        for key, payload in items:
            deliver(key, payload, self._model, self._stats, on_message, self._context)
        return len(items)


def deliver(
    key: str,
    payload: bytes,
    model: type[M],
    stats: DecodeStats,
    on_message: Callable[[str, M], None],
    context: Any = None,
) -> None:
    """Decode `payload` (arrived on `key`) as `model` and hand it on, or count it: as
    malformed, as rejected when it names a robot other than its key's, or when the
    handler fails (a hostile value must never take the process down).
    """
    value = decode(model, payload, stats, context)
    if value is None:
        return
    name = model.__name__
    sender = getattr(value, "robot_id", None)
    keyed = robot_of(key)
    if sender is not None and keyed and sender != keyed:
        stats.count("rejected", name, f"{name} of {sender!r} on {keyed!r}'s key")
        return
    try:
        on_message(key, value)
    except Exception as exc:  # counted and logged, never raised into Zenoh's thread
        stats.count("handler_errors", name, f"{name}: handler failed: {type(exc).__name__}: {exc}")
        log.warning("a %s on %s could not be handled: %s", name, key, exc)
