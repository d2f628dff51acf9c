"""Wire encoding of the messages in `phalanx.messages`, and total decoding.

Two forms: JSON (pydantic) and a packed binary form (1-byte message kind, 1-byte
version, the fixed-size fields in one block, then strings and lists, length-prefixed).
`bench/bench_codec.py` measures both; the packed form is the default because it is
40 % of the bytes of JSON for a RobotState, which is what counts on a robot's WiFi. It is
about as fast to encode and a few microseconds slower to decode (figures in
docs/PERFORMANCE.md), which is noise against a 50 ms control period. JSON stays
available for debugging (`PHALANX_WIRE=json`).

Decoding never raises: a malformed payload, an unknown kind or version, or a value that
fails validation (against the receiver's `FleetBounds`, if it gives them) is dropped and
counted in `DecodeStats`, which also counts what never reached the decoder (a full ring)
and what a receiver refused after it (a message on another robot's key).
"""

from __future__ import annotations

import os
import struct
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Annotated, Any, Final, Literal, TypeVar, get_args, get_origin, get_type_hints

from pydantic import ValidationError

from phalanx.core.peers import IntWidth, PeerFlags, PeerState
from phalanx.wire.messages import (
    AgentEvent,
    AgentReport,
    ClockTick,
    LeaderAnnouncement,
    Message,
    OperatorCommand,
    RobotFlags,
    RobotState,
    ScanMessage,
    SenseFrame,
    VelocityCommand,
)
from phalanx.wire.positions import PoseFixMessage, RelativeFixMessage, TruthMessage

M = TypeVar("M", bound=Message)
WireFormat = Literal["packed", "json"]
JSON_MARK = ord("{")

# (field name, kind); on the wire every fixed-size field comes first, in this order, packed
# by one Struct, then the strings and lists in this order. Kinds: s = string, d = float64,
# I = uint32, b = int8, ? = bool, D = list of float64, B = list of bool, R = list of
# RobotState (each its own packed form, length-prefixed). `version` is the header, not a
# field.
_RECORD_KINDS: Final[dict[object, str]] = {
    str: "s",
    float: "d",
    bool: "?",
    tuple[float, ...]: "D",
    IntWidth(8, signed=True): "b",
    IntWidth(32, signed=False): "I",
}


def record_layout(record: type[Any]) -> tuple[tuple[str, str], ...]:
    """The layout of a shared record's message (`phalanx.core.peers`): its fields in its
    order, each of the kind its type gives (an int: of the width it is annotated with).
    """
    hints = get_type_hints(record, include_extras=True)
    return tuple((f.name, _record_kind(f.name, hints[f.name])) for f in fields(record))


def _record_kind(name: str, hint: object) -> str:
    if get_origin(hint) is Annotated:
        base, *extras = get_args(hint)
        hint = next((e for e in extras if isinstance(e, IntWidth)), base)
    kind = _RECORD_KINDS.get(hint)
    if kind is None:
        raise TypeError(f"{name}: {hint} has no packed kind (an int takes Int8 or UInt32)")
    return kind


# A robot's state and its flags (the fields of it every robot needs), from their records.
_STATE_FIELDS = record_layout(PeerState)
_FLAG_FIELDS = record_layout(PeerFlags)
LAYOUTS: dict[type[Message], tuple[int, tuple[tuple[str, str], ...]]] = {
    RobotState: (1, _STATE_FIELDS),
    ClockTick: (2, (("tick", "I"), ("t_s", "d"), ("dt_s", "d"), ("final", "?"))),
    VelocityCommand: (
        3,
        (("robot_id", "s"), ("tick", "I"), ("stamp_s", "d"), ("v_mps", "d"), ("omega_radps", "d")),
    ),
    SenseFrame: (
        4,
        (
            ("robot_id", "s"),
            ("tick", "I"),
            ("t_s", "d"),
            ("dt_s", "d"),
            ("x_m", "d"),
            ("y_m", "d"),
            ("theta_rad", "d"),
            ("v_mps", "d"),
            ("omega_radps", "d"),
            ("sonar_ranges_m", "D"),
            ("bumpers", "B"),
            ("final", "?"),
            ("fixes", "D"),  # empty (2 bytes each) without simulated positioning
            ("relative", "D"),
            ("peers", "R"),  # empty (2 bytes) unless in lockstep
        ),
    ),
    AgentEvent: (
        5,
        (("robot_id", "s"), ("t_s", "d"), ("source", "s"), ("target", "s"), ("reason", "s")),
    ),
    AgentReport: (
        6,
        (
            ("robot_id", "s"),
            ("steps", "I"),
            ("saturations", "I"),
            ("accel_limited", "I"),
            ("dropped_messages", "I"),
            ("late_peer_steps", "I"),
            ("step_p50_us", "d"),
            ("step_p99_us", "d"),
            ("telemetry_dropped", "I"),
            ("commands_sent", "I"),
        ),
    ),
    # a robot's flags: the fields of its state that RobotFlags has, in the same order
    RobotFlags: (7, _FLAG_FIELDS),
    LeaderAnnouncement: (
        8,
        (
            ("leader_id", "s"),
            ("epoch", "I"),
            ("stamp_s", "d"),
            ("previous_id", "s"),
            ("reason", "s"),
        ),
    ),
    PoseFixMessage: (
        9,
        (
            ("robot_id", "s"),
            ("stamp_s", "d"),
            ("x_m", "d"),
            ("y_m", "d"),
            ("theta_rad", "d"),
            ("std_m", "d"),
            ("std_rad", "d"),
        ),
    ),
    RelativeFixMessage: (
        10,
        (
            ("robot_id", "s"),
            ("target_id", "s"),
            ("stamp_s", "d"),
            ("range_m", "d"),
            ("bearing_rad", "d"),
            ("heading_rad", "d"),
            ("std_range_m", "d"),
            ("std_bearing_rad", "d"),
            ("std_heading_rad", "d"),
        ),
    ),
    ScanMessage: (
        11,
        (
            ("robot_id", "s"),
            ("stamp_s", "d"),
            ("x_m", "d"),
            ("y_m", "d"),
            ("theta_rad", "d"),
            ("ranges_m", "D"),
            ("echo", "B"),
        ),
    ),
    TruthMessage: (
        12,
        (
            ("robot_id", "s"),
            ("stamp_s", "d"),
            ("x_m", "d"),
            ("y_m", "d"),
            ("theta_rad", "d"),
            ("v_mps", "d"),
            ("omega_radps", "d"),
            ("clock_rate", "d"),
            ("source", "s"),
        ),
    ),
    OperatorCommand: (
        13,
        (
            ("robot_id", "s"),
            ("stamp_s", "d"),
            ("twist", "?"),
            ("v_mps", "d"),
            ("omega_radps", "d"),
            ("goal", "?"),
            ("goal_x_m", "d"),
            ("goal_y_m", "d"),
        ),
    ),
}
_SCALAR_KINDS = frozenset("dIb?")
_COUNT = struct.Struct("<H")
# No message phalanx sends comes near this: a SenseFrame of 64 sonars is under 1 kB, and
# in lockstep one that carries the other states of a fleet of MAX_ROBOTS about 170 kB.
MAX_PAYLOAD_BYTES = 256 * 1024


@dataclass(frozen=True)
class _Layout:
    """A message's wire layout: every fixed-size field in one Struct, then the rest."""

    kind_id: int
    fixed_names: tuple[str, ...]
    fixed: struct.Struct
    variable: tuple[tuple[str, str], ...]  # (name, kind) of strings and lists, in order


def _compile(kind_id: int, layout: tuple[tuple[str, str], ...]) -> _Layout:
    fixed = [(n, k) for n, k in layout if k in _SCALAR_KINDS]
    return _Layout(
        kind_id=kind_id,
        fixed_names=tuple(n for n, _ in fixed),
        fixed=struct.Struct("<" + "".join(k for _, k in fixed)),
        variable=tuple((n, k) for n, k in layout if k not in _SCALAR_KINDS),
    )


_COMPILED = {model: _compile(kind_id, layout) for model, (kind_id, layout) in LAYOUTS.items()}


def default_format() -> WireFormat:
    """The wire format in use (`PHALANX_WIRE=json` switches to JSON)."""
    return "json" if os.environ.get("PHALANX_WIRE") == "json" else "packed"


# The packed form of the nested messages packed lately, by identity (a message is frozen):
# a lockstep world puts each robot's state into every other robot's frame, n - 1 times a
# tick, and packs it once. Cleared when full; an entry keeps its message, so an id is
# never another message's while it is in here.
_NESTED: dict[int, tuple[Message, bytes]] = {}
_NESTED_MAX = 4096


def _packed_nested(item: Message) -> bytes:
    hit = _NESTED.get(id(item))
    if hit is not None and hit[0] is item:
        return hit[1]
    raw = _encode_packed(item)
    if len(_NESTED) >= _NESTED_MAX:
        _NESTED.clear()
    _NESTED[id(item)] = (item, raw)
    return raw


def _pack_variable(kind: str, value: Any, out: bytearray) -> None:
    if kind == "R":
        out += _COUNT.pack(len(value))
        for item in value:
            raw = _packed_nested(item)
            out += _COUNT.pack(len(raw))
            out += raw
    elif kind == "s":
        raw = value.encode("utf-8")
        out += _COUNT.pack(len(raw))
        out += raw
    else:
        out += _COUNT.pack(len(value))
        out += struct.pack(f"<{len(value)}{'d' if kind == 'D' else '?'}", *value)


def encode(message: Message, fmt: WireFormat | None = None) -> bytes:
    """Bytes of `message` in the packed (default) or JSON form."""
    if (fmt or default_format()) == "json":
        return message.model_dump_json().encode("utf-8")
    return _encode_packed(message)


def _encode_packed(message: Message) -> bytes:
    wire = _COMPILED[type(message)]
    out = bytearray((wire.kind_id, message.version))  # type: ignore[attr-defined]
    out += wire.fixed.pack(*[getattr(message, n) for n in wire.fixed_names])
    for name, kind in wire.variable:
        _pack_variable(kind, getattr(message, name), out)
    return bytes(out)


def _unpack_variable(kind: str, payload: bytes, offset: int) -> tuple[Any, int]:
    (count,) = _COUNT.unpack_from(payload, offset)
    offset += _COUNT.size
    if kind == "R":
        items = []
        for _ in range(count):
            (size,) = _COUNT.unpack_from(payload, offset)
            offset += _COUNT.size
            if offset + size > len(payload):
                raise struct.error("a nested message runs past the payload")
            items.append(_values(RobotState, payload[offset : offset + size]))
            offset += size
        return items, offset
    if kind == "s":
        end = offset + count
        if end > len(payload):
            raise struct.error("string runs past the payload")
        return payload[offset:end].decode("utf-8"), end
    item = "d" if kind == "D" else "?"
    size = struct.calcsize(f"<{count}{item}")
    return struct.unpack_from(f"<{count}{item}", payload, offset), offset + size


def _decode_packed(model: type[M], payload: bytes, context: Any = None) -> M:
    return model.model_validate(_values(model, payload), context=context)


def _values(model: type[Message], payload: bytes) -> dict[str, Any]:
    """The field values packed in `payload` (not yet validated)."""
    wire = _COMPILED[model]
    if len(payload) < 2 or payload[0] != wire.kind_id:
        raise ValueError(f"expected message kind {wire.kind_id}, got {payload[:1]!r}")
    if payload[1] != 1:
        raise _UnknownVersion(payload[1])
    values = dict(zip(wire.fixed_names, wire.fixed.unpack_from(payload, 2), strict=True))
    offset = 2 + wire.fixed.size
    for name, kind in wire.variable:
        values[name], offset = _unpack_variable(kind, payload, offset)
    if offset != len(payload):
        raise ValueError(f"{len(payload) - offset} trailing bytes")
    return values


class _UnknownVersion(ValueError):
    pass


@dataclass
class DecodeStats:
    """Every payload a process was sent and did not act on, by message kind: malformed
    (including values outside the receiver's bounds), of an unknown version, refused by
    the receiver (`rejected`: on another robot's key), lost in a full ring before it was
    decoded (`ring_dropped`), over its sender's rate on a rate-limited subscription
    (`rate_limited`, also before decoding), or valid but its handler failed
    (`handler_errors`: a bug, counted so it never takes the process down); and the last
    failure's reason.
    """

    ok: Counter[str] = field(default_factory=Counter)
    malformed: Counter[str] = field(default_factory=Counter)
    unknown_version: Counter[str] = field(default_factory=Counter)
    rejected: Counter[str] = field(default_factory=Counter)
    ring_dropped: Counter[str] = field(default_factory=Counter)
    rate_limited: Counter[str] = field(default_factory=Counter)
    handler_errors: Counter[str] = field(default_factory=Counter)  # a bug: should stay 0
    last_error: str = ""

    @property
    def dropped(self) -> int:
        """Payloads dropped for any reason."""
        counters = (
            self.malformed,
            self.unknown_version,
            self.rejected,
            self.ring_dropped,
            self.rate_limited,
            self.handler_errors,
        )
        return sum(sum(c.values()) for c in counters)

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly counters (for status queries)."""
        return {
            "ok": dict(self.ok),
            "malformed": dict(self.malformed),
            "unknown_version": dict(self.unknown_version),
            "rejected": dict(self.rejected),
            "ring_dropped": dict(self.ring_dropped),
            "rate_limited": dict(self.rate_limited),
            "handler_errors": dict(self.handler_errors),
            "dropped": self.dropped,
            "last_error": self.last_error,
        }

    def count(self, reason: str, name: str, text: str) -> None:
        """Count one payload of kind `name` dropped for `reason` (a counter's name)."""
        counter: Counter[str] = getattr(self, reason)
        counter[name] += 1
        self.last_error = text


def decode(
    model: type[M], payload: bytes, stats: DecodeStats | None = None, context: Any = None
) -> M | None:
    """The message in `payload`, or None (counted in `stats`) if it is not a valid one;
    `context` (a `FleetBounds`) holds it against what the receiver knows of its fleet.
    """
    name = model.__name__
    if len(payload) > MAX_PAYLOAD_BYTES:
        _count(stats, "malformed", name, f"{name}: {len(payload)} bytes, over {MAX_PAYLOAD_BYTES}")
        return None
    try:
        if payload[:1] == bytes((JSON_MARK,)):
            message = model.model_validate_json(payload, context=context)
        else:
            message = _decode_packed(model, payload, context)
    except _UnknownVersion as exc:
        _count(stats, "unknown_version", name, f"{name}: unknown version {exc}")
        return None
    except ValidationError as exc:
        reason = "unknown_version" if _only_version(exc) else "malformed"
        _count(stats, reason, name, f"{name}: {_summary(exc)}")
        return None
    except Exception as exc:  # a hostile payload may trip anything: never let it through
        _count(stats, "malformed", name, f"{name}: {type(exc).__name__}: {str(exc)[:200]}")
        return None
    if stats is not None:
        stats.ok[name] += 1
    return message


def _only_version(exc: ValidationError) -> bool:
    return all(e["loc"][:1] == ("version",) for e in exc.errors())


def _summary(exc: ValidationError) -> str:
    first = exc.errors()[0]
    where = ".".join(str(p) for p in first["loc"]) or "<message>"
    more = f" (+{exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
    return f"{where}: {first['msg']}{more}"[:300]


def _count(stats: DecodeStats | None, reason: str, name: str, text: str) -> None:
    if stats is not None:
        stats.count(reason, name, text)


Decoder = Callable[[bytes], Message | None]
