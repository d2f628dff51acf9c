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
import os
import socket
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field

from phalanx.core.errors import TransportError
from phalanx.core.lifecycle import Closing
from phalanx.wire.bounds import FleetBounds
from phalanx.wire.codec import DecodeStats, encode
from phalanx.wire.delivery import (
    KeyBuckets,
    Polled,
    deliver,
    over_rate,
    stamp_filter,
    stamped,
)
from phalanx.wire.messages import Message
from phalanx.wire.security import AccessControl, TlsFiles, apply_security

log = logging.getLogger("phalanx.transport")
PEER_LOWLATENCY = (
    "a peer on the low-latency transport: in a mesh of 20 or more, Zenoh 1.10 was seen to "
    "hang a declaration for good (docs/HARDWARE.md); join the fleet through a router"
)
MAX_STATUS_BYTES = 1024 * 1024
# The largest payload sent on a low-latency session: under Zenoh's 64 KiB batch with room
# for its headers (a fleet's messages are a few hundred bytes; a status reply a few KiB).
LOWLATENCY_MAX_BYTES = 60_000
# A Unix-domain socket's path holds at most this many bytes (Linux's address has room for
# 108 with the terminating NUL, macOS's for 104: the smaller counts).
SOCKET_PATH_MAX_BYTES = 103
RELINK_OPEN_S = 2.0  # how long `FleetSession.relink` waits for a new session's handshake
M = TypeVar("M", bound=Message)
_open_sessions: set[int] = set()
_registry_lock = threading.Lock()
_log_initialised = False


class TransportConfig(BaseModel):
    """How a process joins the fabric. Endpoints like `tcp/127.0.0.1:7447`, or
    `unixsock-stream/<path>` for processes on one machine (see `unix_socket_endpoint`).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    lease_ms: int = Field(default=1000, ge=100, le=3_600_000)
    keep_alive: int = Field(default=4, ge=1, le=100)
    open_timeout_s: float = Field(default=15.0, ge=0.0, le=3600.0)
    # Routers and peers retry their `connect` endpoints forever; a lost link comes back
    # within `retry_max_ms` of the network returning (Zenoh's default waits up to 4 s).
    retry_max_ms: int | None = Field(default=None, ge=100, le=3_600_000)
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


def unix_socket_endpoint(path: Path) -> str:
    """`unixsock-stream/<path>`: a Zenoh link over the Unix-domain socket at `path`.

    Who may connect is whoever the file system lets reach `path`: put it in a directory
    only its user can open. `path` must be absolute and at most `SOCKET_PATH_MAX_BYTES`
    long (a TransportError otherwise).
    """
    size = len(os.fsencode(path))
    if not path.is_absolute() or size > SOCKET_PATH_MAX_BYTES:
        raise TransportError(
            f"a Unix-domain socket needs an absolute path of at most "
            f"{SOCKET_PATH_MAX_BYTES} bytes, not {str(path)!r} ({size} bytes)"
        )
    return f"unixsock-stream/{path}"


def open_session_count() -> int:
    """Sessions opened by this process and not closed yet (tests fail on leaks)."""
    with _registry_lock:
        return len(_open_sessions)


Declare = Callable[[Any], Any]  # declares one entity on a zenoh.Session, returns it


class FleetSession(Closing):
    """A Zenoh session with phalanx's codec, drop counting and liveliness; context manager.

    Everything declared through its methods is declared again by `relink`, on a new Zenoh
    session with the same configuration: the way back for a process that a router
    stopped serving (see `relink`).
    """

    def __init__(self, cfg: TransportConfig) -> None:
        import zenoh

        global _log_initialised
        if not _log_initialised:
            zenoh.init_log_from_env_or("error")
            _log_initialised = True
        self._cfg = cfg
        if cfg.lowlatency and cfg.mode == "peer":
            log.warning(PEER_LOWLATENCY)
        self._session = _open_with_retry(cfg)
        self.stats = DecodeStats()
        self.relinks = 0  # how many times `relink` replaced the Zenoh session
        # What was declared, with how to declare it again (None: held as given, `hold`).
        self._keep: list[tuple[Declare | None, Any]] = []
        self._publishers: dict[tuple[str, bool], Any] = {}  # (key, BLOCK): one each way
        self._lock = threading.RLock()  # the Zenoh session and its entities, swapped whole
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
        payload = self._fits(encode(message), key)
        with self._lock:
            publisher = self._publishers.get((key, reliable_block))
            if publisher is None:
                publisher = self._declare_publisher(key, reliable_block)
            publisher.put(payload)

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
        with self._lock:
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
        self._publishers[key, block] = publisher
        return publisher

    def subscribe(
        self,
        key_expr: str,
        model: type[M],
        on_message: Callable[[str, M], None],
        *,
        context: Any = None,
        rate_hz: float | None = None,
    ) -> None:
        """Call `on_message(key, value)` for every valid message; count the rest.

        `context` (a `FleetBounds`) holds every message against what this process knows
        of its fleet. `rate_hz`: how many messages a second one sender publishes on one
        key; a key is then held to a few times that (`phalanx.wire.delivery.KeyBuckets`),
        and a packed message stamped no later than the newest its key delivered is
        dropped before it takes a token (`StampFilter`), each counted (None: no limit,
        as in lockstep, where the world sets the pace). `on_message` runs on a Zenoh
        thread: it must be quick and must not call Zenoh.
        """
        stats, name = self.stats, model.__name__
        limit = _limit(rate_hz, context)
        stamps = stamp_filter(model, limit)
        handler = stamped(stamps, on_message)

        def callback(sample: Any) -> None:
            key = str(sample.key_expr)
            payload = sample.payload.to_bytes()
            if stamps is not None and stamps.stale(key, payload):
                stats.rate_limited[name] += 1
            elif not over_rate(limit, key, stats, name):
                deliver(key, payload, model, stats, handler, context)

        self._declare(lambda session: session.declare_subscriber(key_expr, callback))

    def subscribe_polled(
        self,
        key_expr: str,
        model: type[M],
        capacity: int,
        *,
        context: Any = None,
        rate_hz: float | None = None,
    ) -> Polled[M]:
        """Hold arriving payloads in a ring of `capacity` (the oldest dropped, and
        counted, when full) until the owner drains and decodes them on its own thread:
        Zenoh's thread only appends bytes (under a microsecond of Python per message),
        which is what a subscription every robot hears from every robot needs.
        `rate_hz` as for `subscribe`: a flood on one key cannot push the others' messages
        out of the ring.
        """
        ring = Polled(model, self.stats, capacity, context, limit=_limit(rate_hz, context))
        self._declare(lambda session: session.declare_subscriber(key_expr, ring.put))
        return ring

    def declare_alive(self, key: str) -> None:
        """Hold a liveliness token on `key` while the session lives."""
        self._declare(lambda session: session.liveliness().declare_token(key))

    def watch_alive(self, key_expr: str, on_change: Callable[[str, bool], None]) -> None:
        """`on_change(key, alive)` on every token appearing (True) or vanishing (False)."""
        import zenoh

        def callback(sample: Any) -> None:
            on_change(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        self._declare(
            lambda session: session.liveliness().declare_subscriber(
                key_expr, callback, history=True
            )
        )

    def serve_status(self, key: str, status: Callable[[], dict[str, Any]]) -> None:
        """Answer queries on `key` with `status()` as JSON."""

        def callback(query: Any) -> None:
            payload = json.dumps(status()).encode("utf-8")
            try:
                query.reply(key, self._fits(payload, key))
            except TransportError as exc:
                query.reply(key, json.dumps({"error": str(exc)}).encode("utf-8"))

        self._declare(lambda session: session.declare_queryable(key, callback))

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
        """Keep an entity declared on `self.zenoh` until `close()` undeclares it; returns it
        (a session holding one cannot `relink`: it could not declare it again).
        """
        with self._lock:
            self._keep.append((None, entity))
        return entity

    def _declare(self, declare: Declare) -> None:
        with self._lock:
            self._keep.append((declare, declare(self._session)))

    @property
    def can_relink(self) -> bool:
        """Whether `relink` could declare everything again: nothing held raw (`hold`),
        no endpoint to listen on (the old session holds it until the new one is open).
        """
        with self._lock:
            return not self._cfg.listen and all(d is not None for d, _ in self._keep)

    def relink(self, open_timeout_s: float = RELINK_OPEN_S) -> bool:
        """Replace the Zenoh session by a new one with the same configuration (a new
        Zenoh id) and declare on it everything declared so far; whether it did.

        Zenoh 1.10 on the low-latency transport, when a router stops past the lease and
        comes back, sometimes re-attaches a client to it while the router drops
        everything the client had declared: the client looks connected and hears
        nothing, for good. A new session starts clean. Publishing goes on meanwhile, on
        the old session until the swap. A new session that cannot be opened within
        `open_timeout_s` (the router still gone) leaves the old one in place.
        """
        with self._lock:
            if self._closed:
                return False
            if self._cfg.listen:  # the new session could not listen where the old one does
                raise TransportError("a session listening on endpoints cannot relink")
            if not self.can_relink:
                raise TransportError("a session holding raw Zenoh entities cannot relink")
        try:
            session = _open_once(self._cfg, open_timeout_s)
        except Exception as exc:  # zenoh raises its own ZError
            log.warning("could not open a new Zenoh session: %s", exc)
            return False
        with self._lock:
            if self._closed:
                session.close()
                return False
            old, self._session = self._session, session
            declares = [d for d, _ in self._keep if d is not None]
            old_entities = [e for _, e in self._keep] + list(self._publishers.values())
            self._keep, self._publishers = [], {}
        # The old session goes first: a token declared twice would be lost to the fleet
        # when the old one's is undeclared, and a subscription twice would hear twice.
        _close_quietly(old, old_entities)
        with self._lock:
            if self._closed:  # `close` closed the new session
                return False
            self._keep[:0] = [(d, d(session)) for d in declares]
            self.relinks += 1
        log.warning("re-opened the Zenoh session (%d entities declared again)", len(declares))
        return True

    def close(self) -> None:
        """Undeclare everything and close the session; safe twice."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            entities = [e for _, e in self._keep] + list(self._publishers.values())
            self._keep.clear()
            self._publishers.clear()
        _close_quietly(self._session, entities, strict=True)
        with _registry_lock:
            _open_sessions.discard(id(self))


def _limit(rate_hz: float | None, context: Any) -> KeyBuckets | None:
    """The per-key rate limit of a subscription (None: none)."""
    if rate_hz is None:
        return None
    bounds = context if isinstance(context, FleetBounds) else None
    return KeyBuckets(rate_hz, bounds=bounds)


def _close_quietly(session: Any, entities: list[Any], *, strict: bool = False) -> None:
    """Undeclare `entities`, newest first, then close `session` (a failure to close is
    raised when `strict`, else logged: a relinked session may be half gone already).
    """
    for entity in reversed(entities):
        _quietly(entity.undeclare)
    if strict:
        session.close()
    else:
        _quietly(session.close)


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


def _open_once(cfg: TransportConfig, open_timeout_s: float) -> Any:
    """One attempt at a session for `cfg`, its handshake bounded by `open_timeout_s`."""
    import zenoh

    conf = zenoh_config(cfg)
    conf.insert_json5("transport/unicast/open_timeout", json.dumps(round(1000 * open_timeout_s)))
    return zenoh.open(conf)


def open_session(cfg: TransportConfig) -> FleetSession:
    """Open a fleet session (use it in a `with` block)."""
    return FleetSession(cfg)


def endpoints(ports: Iterable[int]) -> tuple[str, ...]:
    """Loopback endpoints for `ports`."""
    return tuple(loopback_endpoint(p) for p in ports)
