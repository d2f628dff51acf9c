"""What arrives on a fleet session, on its way to the code that owns it: held to its
sender's rate (`KeyBuckets`), decoded totally and checked (`deliver`), or held raw in a
bounded ring until its owner drains it (`Polled`), and the last few values per robot
(`History`). Every payload is either handed on or counted in the session's `DecodeStats`.

A rate-limited subscription (a ring or a callback) also drops, before it takes a token, a
packed message stamped no later than the newest its key has delivered (`StampFilter`): a
flood of copies of a robot's old state cannot then spend the tokens the robot's own new
states need.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Generic, TypeVar

from phalanx.wire.bounds import FleetBounds
from phalanx.wire.codec import LAYOUTS, DecodeStats, decode
from phalanx.wire.keys import robot_of
from phalanx.wire.messages import Message

log = logging.getLogger("phalanx.transport")
M = TypeVar("M", bound=Message)
# A rate-limited subscription takes from each key this many times the rate its sender
# publishes at, in bursts of what the sender publishes in STALL_S (at least BURST
# messages): the batch that arrives at once after this process or the link stalled on a
# loaded machine. The rest is dropped before it is decoded, and counted
# (`DecodeStats.rate_limited`).
RATE_HEADROOM = 4.0
STALL_S = 5.0
BURST = 8
# Keys with a bucket of their own, at most; a key beyond them, or of a robot outside
# the receiver's fleet (refused when decoded anyway), shares the OTHERS bucket.
MAX_KEYS = 1024
OTHERS = ""
IDLE_S = 10.0  # a key silent this long gives up its bucket to a new one


class KeyBuckets:
    """A token bucket per key (thread-safe): `admit(key)` says whether a message on
    `key` is within `RATE_HEADROOM` x `rate_hz` (messages a second its sender publishes),
    so that a flood on one key cannot crowd the others out of a ring or a Zenoh thread.
    `bounds`: the keys of robots outside this fleet share one bucket.
    """

    def __init__(
        self,
        rate_hz: float,
        *,
        bounds: FleetBounds | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"a rate limit needs a positive rate, not {rate_hz} Hz")
        self.refill_hz = RATE_HEADROOM * rate_hz
        self.burst = max(float(BURST), STALL_S * rate_hz)
        self._members = bounds.robot_ids if bounds is not None else None
        self._clock = clock
        self._lock = threading.Lock()
        self._buckets: dict[str, tuple[float, float]] = {}  # key -> (tokens, when)

    def admit(self, key: str) -> bool:
        """Whether a message arriving now on `key` is within its sender's rate (if so,
        it takes a token).
        """
        now = self._clock()
        with self._lock:
            slot = self._slot(key, now)
            tokens, then = self._buckets.get(slot, (self.burst, now))
            tokens = min(self.burst, tokens + max(0.0, now - then) * self.refill_hz)
            admitted = tokens >= 1.0
            self._buckets[slot] = (tokens - 1.0 if admitted else tokens, now)
            return admitted

    def _slot(self, key: str, now: float) -> str:
        """The bucket `key` draws on: its own, or OTHERS."""
        if key in self._buckets:
            return key
        if self._members is not None and robot_of(key) not in self._members:
            return OTHERS
        if len(self._buckets) >= MAX_KEYS:
            idle = [k for k, (_t, then) in self._buckets.items() if now - then > IDLE_S]
            for gone in idle:
                del self._buckets[gone]
            if len(self._buckets) >= MAX_KEYS:
                return OTHERS
        return key


def over_rate(limit: KeyBuckets | None, key: str, stats: DecodeStats, name: str) -> bool:
    """Whether to drop a message of kind `name` on `key`: over `limit` (then counted)."""
    if limit is None or limit.admit(key):
        return False
    stats.rate_limited[name] += 1
    return True


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


# The fixed-size kinds of the packed form (`phalanx.wire.codec`): packed first, in order.
_FIXED_KINDS = frozenset("dIb?")
_STAMP = struct.Struct("<d")
# A key's stamp filter holds this long (s) after the newest message it delivered.
FRESH_FOR_S = 1.0


def stamp_offset(model: type[Message]) -> int | None:
    """Where a packed `model`'s `stamp_s` lies in its payload (None: it has none)."""
    kinds = ""
    for name, kind in LAYOUTS.get(model, (0, ()))[1]:
        if name == "stamp_s":
            return 2 + struct.calcsize("<" + kinds)  # after the kind and version bytes
        if kind in _FIXED_KINDS:
            kinds += kind
    return None


class StampFilter:
    """The newest stamp each key of a subscription has delivered (a valid message), and
    whether a packed payload is older: read from its bytes, not decoded. A JSON payload,
    or one not of `model`'s kind or version, is left to the decoder. A key that has
    delivered nothing newer for `FRESH_FOR_S` is not filtered until it delivers again
    (its robot's clock stepped back, or a stamp ahead held it: it is silenced that long
    at most). At most `MAX_KEYS` keys are remembered (only keys that delivered a valid
    message are). `stale` runs on Zenoh's thread, `delivered` on the owner's: one
    dictionary read or write each.
    """

    def __init__(
        self, model: type[Message], *, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self._offset = stamp_offset(model)
        self._kind = LAYOUTS[model][0] if model in LAYOUTS else -1
        self._clock = clock
        self._newest: dict[str, tuple[float, float]] = {}  # key -> (stamp, when heard)

    @property
    def active(self) -> bool:
        """Whether `model` carries a stamp to compare."""
        return self._offset is not None

    def stale(self, key: str, payload: bytes) -> bool:
        """Whether `payload` on `key` is packed and stamped no later than the newest."""
        newest = self._newest.get(key)
        offset = self._offset
        if newest is None or offset is None or len(payload) < offset + _STAMP.size:
            return False
        if payload[0] != self._kind or payload[1] != 1:
            return False
        if self._clock() - newest[1] > FRESH_FOR_S:
            return False
        (stamp,) = _STAMP.unpack_from(payload, offset)
        return bool(stamp <= newest[0])  # (NaN: False, left to the decoder)

    def delivered(self, key: str, stamp_s: float) -> None:
        """A valid message stamped `stamp_s` came through on `key`."""
        newest = self._newest.get(key)
        if newest is None and len(self._newest) >= MAX_KEYS:
            return
        now = self._clock()
        if newest is None or stamp_s > newest[0] or now - newest[1] > FRESH_FOR_S:
            self._newest[key] = (stamp_s, now)


class Polled(Generic[M]):
    """A subscription whose payloads wait in a ring of `capacity` until `drain` (see
    `FleetSession.subscribe_polled`). Zenoh's callback only appends the raw payload (no
    decoding on its thread); when the ring is full the oldest payload is dropped and
    counted (`DecodeStats.ring_dropped`). With a `limit`, a payload over its key's rate
    never enters the ring (counted: `DecodeStats.rate_limited`), and neither does a
    packed one stamped no later than the newest its key delivered (`StampFilter`, counted
    the same way, before it takes a token): a robot's messages come in the order it
    stamps them, so an older one is a copy or a replay, and a flood of those would
    otherwise take every token its key gets.
    """

    def __init__(
        self,
        model: type[M],
        stats: DecodeStats,
        capacity: int,
        context: Any = None,
        *,
        limit: KeyBuckets | None = None,
    ) -> None:
        self._model = model
        self._stats = stats
        self._context = context
        self._limit = limit
        self._ring: deque[tuple[str, bytes]] = deque(maxlen=capacity)
        self._lock = threading.Lock()
        self._stamps = stamp_filter(model, limit)

    def put(self, sample: Any) -> None:
        """Zenoh's side: keep the sample's key and payload (the oldest goes if full)."""
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        if self._stamps is not None and self._stamps.stale(key, payload):
            self._stats.rate_limited[self._model.__name__] += 1
            return
        if over_rate(self._limit, key, self._stats, self._model.__name__):
            return
        item = (key, payload)
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
        handler = stamped(self._stamps, on_message)
        for key, payload in items:
            deliver(key, payload, self._model, self._stats, handler, self._context)
        return len(items)


def stamp_filter(model: type[Message], limit: KeyBuckets | None) -> StampFilter | None:
    """The stamp filter a rate-limited subscription to `model` applies (None: none, for
    a subscription without a limit or a model without a stamp).
    """
    stamps = StampFilter(model)
    return stamps if limit is not None and stamps.active else None


def stamped(
    stamps: StampFilter | None, on_message: Callable[[str, M], None]
) -> Callable[[str, M], None]:
    """`on_message`, noting each valid message's stamp in `stamps` first."""
    if stamps is None:
        return on_message

    def handler(key: str, value: M) -> None:
        stamps.delivered(key, float(getattr(value, "stamp_s", -math.inf)))
        on_message(key, value)

    return handler


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
