"""What a robot shares with its fleet is defined once, as `PeerState`: its flags, the wire
models and their packed layouts follow that definition and may not drift from it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal, get_args, get_origin, get_type_hints

import pytest
from annotated_types import Ge, Le
from pydantic.fields import FieldInfo

from phalanx.core.peers import (
    FLAG_FIELDS,
    STATE_FIELDS,
    IntWidth,
    PeerFlags,
    PeerState,
)
from phalanx.wire.codec import LAYOUTS, record_layout
from phalanx.wire.messages import Message, RobotFlags, RobotState

WIDTHS = {"b": IntWidth(8, signed=True), "I": IntWidth(32, signed=False)}
PLAIN = {"s": str, "d": float, "?": bool, "D": tuple[float, ...]}
PAIRS = [(RobotState, PeerState), (RobotFlags, PeerFlags)]


def _declared(record: type[Any]) -> list[tuple[str, object, object]]:
    """(name, annotated type, default) of each of `record`'s fields, in order."""
    hints = get_type_hints(record, include_extras=True)
    return [(f.name, hints[f.name], f.default) for f in dataclasses.fields(record)]


def _int_range(name: str, info: FieldInfo) -> tuple[int, int]:
    """The lowest and highest value the wire lets an int field hold."""
    if get_origin(info.annotation) is Literal:
        values = get_args(info.annotation)
        return min(values), max(values)
    assert info.annotation is int, f"{name}: an int on the record, {info.annotation} on the wire"
    lows = [m.ge for m in info.metadata if isinstance(m, Ge)]
    highs = [m.le for m in info.metadata if isinstance(m, Le)]
    assert lows, f"{name}: an int field on the wire needs a lower bound"
    assert highs, f"{name}: an int field on the wire needs an upper bound"
    return max(lows), min(highs)


def test_the_flags_are_fields_of_the_state_declared_alike_in_its_order() -> None:
    state = _declared(PeerState)
    flags = _declared(PeerFlags)
    assert flags == [field for field in state if field[0] in FLAG_FIELDS]
    assert tuple(name for name, _, _ in state) == STATE_FIELDS


@pytest.mark.parametrize(("model", "record"), PAIRS, ids=["state", "flags"])
def test_the_wire_model_declares_the_records_fields_with_its_defaults(
    model: type[Message], record: type[Any]
) -> None:
    wire = {name: info for name, info in model.model_fields.items() if name != "version"}
    assert tuple(wire) == tuple(f.name for f in dataclasses.fields(record))
    for f in dataclasses.fields(record):
        required = f.default is dataclasses.MISSING
        assert wire[f.name].is_required() == required, f.name
        assert required or wire[f.name].default == f.default, f.name


@pytest.mark.parametrize(("model", "record"), PAIRS, ids=["state", "flags"])
def test_each_wire_field_fits_the_kind_the_record_packs_it_in(
    model: type[Message], record: type[Any]
) -> None:
    for name, kind in record_layout(record):
        info = model.model_fields[name]
        if kind in WIDTHS:
            low, high = _int_range(name, info)
            assert WIDTHS[kind].low <= low <= high <= WIDTHS[kind].high, name
        else:
            assert info.annotation == PLAIN[kind], name


def test_the_packed_layouts_are_generated_from_the_records() -> None:
    assert LAYOUTS[RobotState] == (1, record_layout(PeerState))
    assert LAYOUTS[RobotFlags] == (7, record_layout(PeerFlags))
    assert tuple(name for name, _ in record_layout(PeerState)) == STATE_FIELDS
    assert tuple(name for name, _ in record_layout(PeerFlags)) == FLAG_FIELDS


def test_an_int_without_a_width_has_no_packed_kind() -> None:
    @dataclass(frozen=True)
    class Loose:
        count: int

    with pytest.raises(TypeError, match="Int8 or UInt32"):
        record_layout(Loose)


def _other_than_defaults() -> dict[str, Any]:
    """A value for each field of the state, none its default nor another field's."""
    values: dict[str, Any] = {}
    for i, (name, kind) in enumerate(record_layout(PeerState), start=2):
        values[name] = {"s": f"v{i}", "d": i + 0.5, "?": None, "D": (i + 0.25,)}.get(kind, i)
    for f in dataclasses.fields(PeerState):
        if values[f.name] is None:
            values[f.name] = not f.default
    return values


def test_the_flags_and_the_conversions_carry_every_field() -> None:
    values = _other_than_defaults()
    state = PeerState(**values)
    assert dataclasses.asdict(state) == values
    assert dataclasses.asdict(state.flags()) == {name: values[name] for name in FLAG_FIELDS}
    message = RobotState.model_construct(**values)  # (unvalidated: the values are no robot's)
    assert message.peer() == state
    assert message.flags().peer() == state.flags()
