"""The Zenoh fabric: session configuration and a session wrapper (the keys are built in
`phalanx.wire.keys`).

Callbacks never call Zenoh nor block: they decode and hand values to thread-safe
structures (Zenoh documents blocking in a callback as a deadlock risk).
"""

from __future__ import annotations

import contextlib
import json
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
from phalanx.wire.messages import Message

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
    """The last few decoded values per robot, filled by a callback, read by the loop."""

    def __init__(self, depth: int = 8) -> None:
        self._lock = threading.RLock()  # `wait` evaluates predicates that read values
        self._values: dict[str, deque[Any]] = {}
        self._depth = depth
        self._arrived = threading.Condition(self._lock)

    def push(self, robot_id: str, value: Any) -> None:
        """Add a value (callback side)."""
        with self._arrived:
            self._values.setdefault(robot_id, deque(maxlen=self._depth)).append(value)
            self._arrived.notify_all()

    def values(self, robot_id: str) -> list[Any]:
        """A copy of the values held for `robot_id`, oldest first."""
        with self._lock:
            return list(self._values.get(robot_id, ()))

    def wait(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        """Block until `predicate()` holds (checked on every arrival) or the timeout."""
        with self._arrived:
            return self._arrived.wait_for(predicate, timeout_s)

    def forget(self, robot_id: str) -> None:
        """Drop everything held for `robot_id`."""
        with self._lock:
            self._values.pop(robot_id, None)


class Polled(Generic[M]):
    """A subscription whose messages wait in a ring until `drain` (see
    `FleetSession.subscribe_polled`).
    """

    def __init__(self, subscriber: Any, model: type[M], stats: DecodeStats) -> None:
        self._subscriber = subscriber
        self._model = model
        self._stats = stats

    def drain(self, on_message: Callable[[str, M], None]) -> int:
        """Call `on_message(key, value)` for every valid message waiting (malformed ones
        counted); how many samples were taken.
        """
        taken = 0
        while (sample := self._subscriber.try_recv()) is not None:
            taken += 1
            _deliver(sample, self._model, self._stats, on_message)
        return taken


def _deliver(
    sample: Any, model: type[M], stats: DecodeStats, on_message: Callable[[str, M], None]
) -> None:
    """Decode a Zenoh sample as `model` and hand it on, or count it as malformed."""
    value = decode(model, sample.payload.to_bytes(), stats)
    if value is not None:
        on_message(str(sample.key_expr), value)


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
        publisher.put(encode(message))

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
        self, key_expr: str, model: type[M], on_message: Callable[[str, M], None]
    ) -> None:
        """Call `on_message(key, value)` for every valid message; count the rest.

        `on_message` runs on a Zenoh thread: it must be quick and must not call Zenoh.
        """
        stats = self.stats

        def callback(sample: Any) -> None:
            _deliver(sample, model, stats, on_message)

        self._keep.append(self._session.declare_subscriber(key_expr, callback))

    def subscribe_polled(self, key_expr: str, model: type[M], capacity: int) -> Polled[M]:
        """Hold arriving messages in a ring of `capacity` (the oldest dropped when full)
        until the owner drains them on its own thread: no Zenoh thread wakes Python per
        message, which is what a subscription every robot hears from every robot needs.
        """
        import zenoh

        subscriber = self._session.declare_subscriber(
            key_expr, zenoh.handlers.RingChannel(capacity)
        )
        self._keep.append(subscriber)
        return Polled(subscriber, model, self.stats)

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
            query.reply(key, json.dumps(status()).encode("utf-8"))

        self._keep.append(self._session.declare_queryable(key, callback))

    def query_status(self, key: str, timeout_s: float = 2.0) -> list[dict[str, Any]]:
        """Every status reply to `key` within `timeout_s`."""
        replies = []
        for reply in self._session.get(key, timeout=timeout_s):
            if reply.ok is not None:
                replies.append(json.loads(reply.ok.payload.to_bytes()))
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
                raise TransportError(f"cannot open a Zenoh session with {cfg}: {exc}") from exc
            time.sleep(delay_s)
            delay_s = min(1.0, delay_s * 2)


def open_session(cfg: TransportConfig) -> FleetSession:
    """Open a fleet session (use it in a `with` block)."""
    return FleetSession(cfg)


def endpoints(ports: Iterable[int]) -> tuple[str, ...]:
    """Loopback endpoints for `ports`."""
    return tuple(loopback_endpoint(p) for p in ports)
