"""The Zenoh fabric: session configuration and a session wrapper (the keys are built in
`phalanx.wire.keys`).

Callbacks never call Zenoh nor block: they decode and hand values to thread-safe
structures (Zenoh documents blocking in a callback as a deadlock risk). Whatever arrives
is hostile until checked: every payload is decoded totally (against the receiver's
`FleetBounds` when it gives them), a message on a robot's key must be that robot's, a
handler that fails is counted, never let out into Zenoh's thread, and a ring that
overflows counts what it lost: every payload is either acted on or counted in the
session's `DecodeStats`.
"""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from typing import Any, Generic, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field

from phalanx.core.errors import TransportError
from phalanx.core.lifecycle import Closing
from phalanx.wire.codec import DecodeStats, decode, encode
from phalanx.wire.keys import robot_of
from phalanx.wire.messages import Message
from phalanx.wire.security import AccessControl, TlsFiles, apply_security

log = logging.getLogger("phalanx.transport")
MAX_STATUS_BYTES = 1024 * 1024
# The largest payload sent on a low-latency session: under Zenoh's 64 KiB batch with room
# for its headers (a fleet's messages are a few hundred bytes; a status reply a few KiB).
LOWLATENCY_MAX_BYTES = 60_000
M = TypeVar("M", bound=Message)
_open_sessions: set[int] = set()
_registry_lock = threading.Lock()
_log_initialised = False


class TransportConfig(BaseModel):
    """How a process joins the fabric. Endpoints like `tcp/127.0.0.1:7447`."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    lease_ms: int = Field(default=1000, ge=100)
    keep_alive: int = Field(default=4, ge=1)
    open_timeout_s: float = Field(default=15.0, ge=0.0)
    # Routers and peers retry their `connect` endpoints forever; a lost link comes back
    # within `retry_max_ms` of the network returning (Zenoh's default waits up to 4 s).
    retry_max_ms: int | None = Field(default=None, ge=100)
    # Multicast scouting in router mode: connect to routers found that way, one link per
    # pair (only the router with the greater Zenoh id connects).
    autoconnect_routers: bool = False
    # `tls/` endpoints: this process's identity; a router's access-control list.
    tls: TlsFiles | None = None
    acl: AccessControl | None = None
    # Zenoh's low-latency transport: a put writes its message to the link itself (no
    # transmission queue, no batching thread to wake: about half the CPU and latency of a
    # round trip here), no priorities, no fragmentation. For a fleet on one machine
    # (`phalanx up`): nothing bulky shares its links, every message is far under one
    # batch, and a process that stops is dropped by its lease. A message over a batch
    # would be lost and the link reset, so the session refuses to send one (see
    # `LOWLATENCY_MAX_BYTES`). Give it to every process of the fleet.
    lowlatency: bool = False


def zenoh_config(cfg: TransportConfig) -> Any:
    """A zenoh.Config for `cfg` (values inserted as JSON5 text, as Zenoh 1.x wants)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(cfg.mode))
    conf.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    # A lost robot must be noticed in about a second, not Zenoh's default 10 s.
    conf.insert_json5("transport/link/tx/lease", json.dumps(cfg.lease_ms))
    conf.insert_json5("transport/link/tx/keep_alive", json.dumps(cfg.keep_alive))
    if cfg.retry_max_ms is not None:
        retry = {
            "period_init_ms": min(250, cfg.retry_max_ms),
            "period_max_ms": cfg.retry_max_ms,
            "period_increase_factor": 2,
        }
        conf.insert_json5("connect/retry", json.dumps(retry))
    if cfg.autoconnect_routers:
        autoconnect = {"router": ["router"], "peer": ["router", "peer"]}
        conf.insert_json5("scouting/multicast/autoconnect", json.dumps(autoconnect))
        strategy = {"router": {"to_router": "greater-zid", "to_peer": "always"}}
        conf.insert_json5("scouting/multicast/autoconnect_strategy", json.dumps(strategy))
    if cfg.lowlatency:  # Zenoh refuses the low-latency transport with priorities on
        conf.insert_json5("transport/unicast/lowlatency", "true")
        conf.insert_json5("transport/unicast/qos/enabled", "false")
    apply_security(conf, cfg.tls, cfg.acl)
    return conf


def free_tcp_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def loopback_endpoint(port: int) -> str:
    """`tcp/127.0.0.1:<port>`."""
    return f"tcp/127.0.0.1:{port}"


def open_session_count() -> int:
    """Sessions opened by this process and not closed yet (tests fail on leaks)."""
    with _registry_lock:
        return len(_open_sessions)


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


def _deliver(
    sample: Any,
    model: type[M],
    stats: DecodeStats,
    on_message: Callable[[str, M], None],
    context: Any = None,
) -> None:
    """Decode a Zenoh sample as `model` and hand it on (see `deliver`)."""
    deliver(str(sample.key_expr), sample.payload.to_bytes(), model, stats, on_message, context)


class FleetSession(Closing):
    """A Zenoh session with phalanx's codec, drop counting and liveliness; context manager."""

    def __init__(self, cfg: TransportConfig) -> None:
        import zenoh

        global _log_initialised
        if not _log_initialised:
            zenoh.init_log_from_env_or("error")
            _log_initialised = True
        self._session = _open_with_retry(cfg)
        self.stats = DecodeStats()
        self._keep: list[Any] = []
        self._publishers: dict[str, Any] = {}
        self._max_bytes = LOWLATENCY_MAX_BYTES if cfg.lowlatency else None
        self._closed = False
        with _registry_lock:
            _open_sessions.add(id(self))

    @property
    def zenoh(self) -> Any:
        """The underlying zenoh.Session."""
        return self._session

    def publish(self, key: str, message: Message, *, reliable_block: bool = False) -> None:
        """Put `message` on `key` (express; BLOCK congestion for must-arrive messages)."""
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self._declare_publisher(key, reliable_block)
        publisher.put(self._fits(encode(message), key))

    def _fits(self, payload: bytes, key: str) -> bytes:
        """`payload`, if this session's links carry it whole (else a TransportError)."""
        if self._max_bytes is not None and len(payload) > self._max_bytes:
            raise TransportError(
                f"{key}: a low-latency session sends at most {self._max_bytes} bytes a "
                f"message, this one has {len(payload)}"
            )
        return payload

    def publish_raw(self, key: str, payload: bytes) -> None:
        """Put raw bytes (tests inject malformed payloads with this)."""
        self._session.put(key, payload)

    def _declare_publisher(self, key: str, block: bool) -> Any:
        import zenoh

        congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        publisher = self._session.declare_publisher(
            key,
            express=True,
            congestion_control=congestion,
            priority=zenoh.Priority.REAL_TIME,
        )
        self._publishers[key] = publisher
        return publisher

    def subscribe(
        self,
        key_expr: str,
        model: type[M],
        on_message: Callable[[str, M], None],
        *,
        context: Any = None,
    ) -> None:
        """Call `on_message(key, value)` for every valid message; count the rest.

        `context` (a `FleetBounds`) holds every message against what this process knows
        of its fleet. `on_message` runs on a Zenoh thread: it must be quick and must not
        call Zenoh.
        """
        stats = self.stats

        def callback(sample: Any) -> None:
            _deliver(sample, model, stats, on_message, context)

        self._keep.append(self._session.declare_subscriber(key_expr, callback))

    def subscribe_polled(
        self, key_expr: str, model: type[M], capacity: int, *, context: Any = None
    ) -> Polled[M]:
        """Hold arriving payloads in a ring of `capacity` (the oldest dropped, and
        counted, when full) until the owner drains and decodes them on its own thread:
        Zenoh's thread only appends bytes (under a microsecond of Python per message),
        which is what a subscription every robot hears from every robot needs.
        """
        ring = Polled(model, self.stats, capacity, context)
        self._keep.append(self._session.declare_subscriber(key_expr, ring.put))
        return ring

    def declare_alive(self, key: str) -> None:
        """Hold a liveliness token on `key` while the session lives."""
        self._keep.append(self._session.liveliness().declare_token(key))

    def watch_alive(self, key_expr: str, on_change: Callable[[str, bool], None]) -> None:
        """`on_change(key, alive)` on every token appearing (True) or vanishing (False)."""
        import zenoh

        def callback(sample: Any) -> None:
            on_change(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        liveliness = self._session.liveliness()
        self._keep.append(liveliness.declare_subscriber(key_expr, callback, history=True))

    def serve_status(self, key: str, status: Callable[[], dict[str, Any]]) -> None:
        """Answer queries on `key` with `status()` as JSON."""

        def callback(query: Any) -> None:
            payload = json.dumps(status()).encode("utf-8")
            try:
                query.reply(key, self._fits(payload, key))
            except TransportError as exc:
                query.reply(key, json.dumps({"error": str(exc)}).encode("utf-8"))

        self._keep.append(self._session.declare_queryable(key, callback))

    def query_status(self, key: str, timeout_s: float = 2.0) -> list[dict[str, Any]]:
        """Every status reply to `key` within `timeout_s` (a reply that is not a JSON
        object of reasonable size is skipped and counted in `stats`).
        """
        replies = []
        for reply in self._session.get(key, timeout=timeout_s):
            if reply.ok is None:
                continue
            raw = reply.ok.payload.to_bytes()
            try:
                value = json.loads(raw) if len(raw) <= MAX_STATUS_BYTES else None
            except (ValueError, RecursionError):
                value = None
            if isinstance(value, dict):
                replies.append(value)
            else:
                self.stats.count("malformed", "status", f"status reply on {reply.ok.key_expr}")
        return replies

    def hold(self, entity: Any) -> Any:
        """Keep an entity declared on `self.zenoh` until `close()` undeclares it; returns it."""
        self._keep.append(entity)
        return entity

    def close(self) -> None:
        """Undeclare everything and close the session; safe twice."""
        if self._closed:
            return
        self._closed = True
        for entity in reversed(self._keep + list(self._publishers.values())):
            _quietly(entity.undeclare)
        self._keep.clear()
        self._publishers.clear()
        self._session.close()
        with _registry_lock:
            _open_sessions.discard(id(self))


def _quietly(action: Callable[[], object]) -> None:
    with contextlib.suppress(Exception):  # already gone during shutdown is fine
        action()


def _open_with_retry(cfg: TransportConfig) -> Any:
    """Open a session, retrying while the endpoints it connects to are not up yet."""
    import zenoh

    deadline = time.monotonic() + cfg.open_timeout_s
    delay_s = 0.05
    while True:
        try:
            return zenoh.open(zenoh_config(cfg))
        except Exception as exc:  # zenoh raises its own ZError
            if time.monotonic() + delay_s > deadline:
                shown = cfg.model_dump(exclude={"acl"}, exclude_defaults=True)
                raise TransportError(f"cannot open a Zenoh session with {shown}: {exc}") from exc
            time.sleep(delay_s)
            delay_s = min(1.0, delay_s * 2)


def open_session(cfg: TransportConfig) -> FleetSession:
    """Open a fleet session (use it in a `with` block)."""
    return FleetSession(cfg)


def endpoints(ports: Iterable[int]) -> tuple[str, ...]:
    """Loopback endpoints for `ports`."""
    return tuple(loopback_endpoint(p) for p in ports)
