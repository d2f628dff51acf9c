"""Hostile payloads for every wire message, as hypothesis strategies built from the wire
models themselves: random bytes, valid payloads truncated or with bits flipped, and
schema-shaped messages whose fields take extreme values (the largest floats, huge and
negative integers, strings that are no robot's id, long lists), in both wire forms.

Used by the fault tier (`tests/faults/test_fuzz_keys.py`, a bounded sample) and by the
campaign (`bench/bench_fuzz.py`, 10^5 payloads per key).
"""

from __future__ import annotations

import json
import struct
import sys
import types
import typing
from typing import Any, Literal, get_args, get_origin

from hypothesis import strategies as st

from phalanx.wire.codec import encode
from phalanx.wire.messages import Message

FLOAT_MAX = sys.float_info.max
EXTREME_FLOATS = (0.0, -0.0, 1e-300, -1e-300, 1e308, -1e308, FLOAT_MAX, -FLOAT_MAX,
                  2.0**31, 2.0**53, -2.0**53, 1e9, -1e9)  # fmt: skip
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
        return st.lists(inner, max_size=80).map(tuple) | st.just(())
    if annotation is bool:
        return st.booleans()
    if annotation is int:
        return st.sampled_from(EXTREME_INTS) | st.integers(-(2**70), 2**70)
    if annotation is float:
        return (
            st.sampled_from(EXTREME_FLOATS)
            | st.floats(allow_nan=False, allow_infinity=False)
            | st.floats(-1e3, 1e3)
        )
    if annotation is str:
        return st.sampled_from(ODD_TEXT) | st.text(max_size=40) | st.sampled_from(
            ("r1", "r2", "r3", "HOLD", "NAVIGATE", "FORMATION_TRACK")
        )
    if annotation is type(None):
        return st.none()
    return st.none()


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
        return encode(model.model_construct(**values), "packed")
    except (struct.error, TypeError, ValueError, OverflowError, AttributeError, KeyError):
        return None  # not representable in the packed form: JSON only


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


def mutated(valid: st.SearchStrategy[bytes]) -> st.SearchStrategy[bytes]:
    """Valid payloads truncated, extended or with bits flipped."""

    def truncate(data: st.DataObject, raw: bytes) -> bytes:
        return raw[: data.draw(st.integers(0, max(0, len(raw) - 1)))]

    def flip(data: st.DataObject, raw: bytes) -> bytes:
        out = bytearray(raw)
        for _ in range(data.draw(st.integers(1, 8))):
            if out:
                i = data.draw(st.integers(0, len(out) - 1))
                out[i] ^= 1 << data.draw(st.integers(0, 7))
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


def hostile_payloads(
    model: type[Message], valid: st.SearchStrategy[bytes]
) -> st.SearchStrategy[bytes]:
    """Everything a hostile peer might send on a key carrying `model`."""
    return st.one_of(
        st.binary(max_size=300),
        extreme_payloads(model),
        mutated(valid),
        mutated(extreme_payloads(model)),
        valid,
    )
