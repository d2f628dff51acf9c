"""Hostile payloads for every wire message, as hypothesis strategies built from the wire
models themselves: random bytes, valid payloads truncated or with bits flipped,
schema-shaped messages whose fields all take extreme values (the largest floats, huge and
negative integers, strings that are no robot's id, long lists), and valid messages with
one to three fields swapped for such values (`final` set, a stamp at 1e308, an epoch at
2**32-1, a robot outside the fleet), in both wire forms.

Used by the fault tier (`tests/faults/test_fuzz_keys.py`, a bounded sample) and by the
campaign (`bench/bench_fuzz.py`, 10^5 payloads per key).
"""

from __future__ import annotations

import json
import struct
import sys
import types
import typing
from collections.abc import Callable
from typing import Any, Literal, get_args, get_origin

from hypothesis import strategies as st

from phalanx.wire.codec import encode
from phalanx.wire.messages import Message

FLOAT_MAX = sys.float_info.max
# An index into something whose length varies with the moment (a payload, the valid
# messages now): drawn independently of that length, so hypothesis can replay a draw.
_index = st.integers(0, 2**16)
EXTREME_FLOATS = (
    0.0,
    -0.0,
    1e-300,
    -1e-300,
    1e308,
    -1e308,
    FLOAT_MAX,
    -FLOAT_MAX,
    2.0**31,
    2.0**53,
    -(2.0**53),
    1e9,
    -1e9,
)
EXTREME_INTS = (-1, 0, 1, 2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**40, 2**63 - 1, 2**64, -(2**63))
ODD_TEXT = ("", "r!", "b1", "r9", "r1/../x", "*", "r" * 65, "\x00", "é", "r1\n", "world")


def _annotation_strategy(annotation: Any, name: str) -> st.SearchStrategy[Any]:
    """Extreme values of the type a field is annotated with."""
    origin = get_origin(annotation)
    if origin is typing.Annotated:
        return _annotation_strategy(get_args(annotation)[0], name)
    if origin is Literal:
        return st.sampled_from(get_args(annotation)) | st.integers(-3, 300)
    if origin in (typing.Union, types.UnionType):
        return st.one_of([_annotation_strategy(a, name) for a in get_args(annotation)])
    if origin is tuple:
        item = get_args(annotation)[0]
        inner = _annotation_strategy(item, name)
        longest = 4 if _nested(item) else 80
        return st.lists(inner, max_size=longest).map(tuple) | st.just(())
    if _nested(annotation):  # a message inside a message (a frame's relayed states)
        return fields_strategy(annotation)
    if annotation is bool:
        return st.booleans()
    if annotation is int:
        extremes = st.sampled_from(EXTREME_INTS)
        return extremes | extremes | st.integers(-(2**70), 2**70)
    if annotation is float:
        return (
            st.sampled_from(EXTREME_FLOATS)
            | st.floats(allow_nan=False, allow_infinity=False)
            | st.floats(-1e3, 1e3)
        )
    if annotation is str:
        return (
            st.sampled_from(ODD_TEXT)
            | st.text(max_size=40)
            | st.sampled_from(("r1", "r2", "r3", "HOLD", "NAVIGATE", "FORMATION_TRACK"))
        )
    if annotation is type(None):
        return st.none()
    return st.none()


def _nested(annotation: Any) -> bool:
    return isinstance(annotation, type) and issubclass(annotation, Message)


def fields_strategy(model: type[Message]) -> st.SearchStrategy[dict[str, Any]]:
    """Every field of `model` with an extreme value of its type (version kept at 1)."""
    parts = {
        name: _annotation_strategy(info.annotation, name)
        for name, info in model.model_fields.items()
        if name != "version"
    }
    return st.fixed_dictionaries(parts)


def _packed(model: type[Message], values: dict[str, Any]) -> bytes | None:
    try:
        return encode(model.model_construct(**_messages_within(model, values)), "packed")
    except (struct.error, TypeError, ValueError, OverflowError, AttributeError, KeyError):
        return None  # not representable in the packed form: JSON only


def _messages_within(model: type[Message], values: dict[str, Any]) -> dict[str, Any]:
    """`values` with the fields that hold messages (a frame's relayed states) built as
    such from their dicts, unchecked, as `model_construct` builds the outer one."""
    out = dict(values)
    for name, info in model.model_fields.items():
        args = get_args(info.annotation)
        if get_origin(info.annotation) is tuple and args and _nested(args[0]):
            items = values.get(name, ())
            out[name] = [args[0].model_construct(**v) if isinstance(v, dict) else v for v in items]
    return out


def _json(values: dict[str, Any]) -> bytes:
    return json.dumps({"version": 1, **values}).encode("utf-8")


def extreme_payloads(model: type[Message]) -> st.SearchStrategy[bytes]:
    """Schema-shaped messages with extreme field values, JSON or packed."""

    def forms(values: dict[str, Any]) -> st.SearchStrategy[bytes]:
        packed = _packed(model, values)
        options = [st.just(_json(values))]
        if packed is not None:
            options.append(st.just(packed))
        return st.one_of(options)

    return fields_strategy(model).flatmap(forms)


def perturbed(
    model: type[Message], messages: Callable[[], list[Message]]
) -> st.SearchStrategy[bytes]:
    """Valid messages (of the moment: `messages()` is asked at each draw) with one to
    three fields swapped for extreme values of their type, JSON or packed."""
    fields = fields_strategy(model)

    @st.composite
    def one(draw: st.DrawFn) -> bytes:
        now = messages()  # (draws never depend on it: hypothesis replays them)
        values = now[draw(_index) % len(now)].model_dump(exclude={"version"})
        extreme = draw(fields)
        names = sorted(extreme)
        for name in draw(st.lists(st.sampled_from(names), min_size=1, max_size=3, unique=True)):
            values[name] = extreme[name]
        packed = _packed(model, values)
        if packed is not None and draw(st.booleans()):
            return packed
        return _json(values)

    return one()


def encoded(messages: Callable[[], list[Message]]) -> st.SearchStrategy[bytes]:
    """The valid messages of the moment themselves, in either form."""

    def forms(_: None) -> list[bytes]:
        now = messages()
        out = [m.model_dump_json().encode() for m in now]
        out += [p for m in now if (p := _packed(type(m), m.model_dump(exclude={"version"})))]
        return out

    return _index.map(lambda i: (lambda all_: all_[i % len(all_)])(forms(None)))


def mutated(valid: st.SearchStrategy[bytes]) -> st.SearchStrategy[bytes]:
    """Valid payloads truncated, extended or with bits flipped."""

    def truncate(data: st.DataObject, raw: bytes) -> bytes:
        return raw[: data.draw(_index) % max(1, len(raw))]

    def flip(data: st.DataObject, raw: bytes) -> bytes:
        out = bytearray(raw)
        for _ in range(data.draw(st.integers(1, 8))):
            i, bit = data.draw(_index), data.draw(st.integers(0, 7))
            if out:
                out[i % len(out)] ^= 1 << bit
        return bytes(out)

    @st.composite
    def one(draw: st.DrawFn) -> bytes:
        raw = draw(valid)
        data = draw(st.data())
        how = draw(st.sampled_from(("truncate", "flip", "extend", "version")))
        if how == "truncate":
            return truncate(data, raw)
        if how == "flip":
            return flip(data, raw)
        if how == "extend":
            return raw + draw(st.binary(min_size=1, max_size=16))
        if raw[:1] == b"{":
            return raw.replace(b'"version": 1', b'"version": 2', 1)
        return raw[:1] + bytes([draw(st.integers(0, 255))]) + raw[2:]

    return one()


def _extremes(annotation: Any) -> list[Any]:
    """The boundary values of a field's type, for the sweep."""
    origin = get_origin(annotation)
    if origin is typing.Annotated:
        return _extremes(get_args(annotation)[0])
    if origin is Literal:
        return [*get_args(annotation), 0, 2, -2, 255]
    if origin in (typing.Union, types.UnionType):
        return [v for a in get_args(annotation) for v in _extremes(a)]
    if origin is tuple:
        items = _extremes(get_args(annotation)[0])
        return [(), tuple(items), (items[0],) * 70] if items else [()]
    if _nested(annotation):  # a message inside a message: empty, or each field's extremes
        fields = annotation.model_fields
        return [{}, *({n: v} for n, f in fields.items() for v in _extremes(f.annotation)[:3])]
    if annotation is bool:
        return [True, False]
    if annotation is int:
        return list(EXTREME_INTS)
    if annotation is float:
        return list(EXTREME_FLOATS)
    if annotation is str:
        return list(ODD_TEXT)
    return [None]


def boundary_sweep(model: type[Message]) -> list[tuple[str, Any, str]]:
    """Each field of `model` at each boundary value of its type: (field, value, form), to
    set on a valid message of the moment with `swept`."""
    out = []
    for name, info in model.model_fields.items():
        if name != "version":
            out += [(name, v, f) for v in _extremes(info.annotation) for f in ("json", "packed")]
    return out


def swept(message: Message, name: str, value: Any, form: str) -> bytes:
    """`message` with field `name` set to `value`, in `form` (JSON if it cannot pack)."""
    values = {**message.model_dump(exclude={"version"}), name: value}
    packed = _packed(type(message), values) if form == "packed" else None
    return packed if packed is not None else _json(values)


def hostile_payloads(
    model: type[Message], messages: Callable[[], list[Message]]
) -> st.SearchStrategy[bytes]:
    """Everything a hostile peer might send on a key carrying `model`, around the valid
    `messages()` of the moment."""
    valid = encoded(messages)
    return st.one_of(
        st.binary(max_size=300),
        extreme_payloads(model),
        perturbed(model, messages),  # the most telling kind: three times the share
        perturbed(model, messages),
        perturbed(model, messages),
        mutated(valid),
        mutated(extreme_payloads(model)),
        valid,
    )
