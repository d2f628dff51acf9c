"""`quick_init`: the frozen dataclasses a step builds by the dozen keep the generated
`__init__`'s signature, defaults and effect, and stay frozen.
"""

from __future__ import annotations

import dataclasses
import inspect

import pytest

from phalanx.agents.behaviours.base import Moment
from phalanx.agents.behaviours.context import StackContext
from phalanx.agents.control.common import FollowerInput
from phalanx.agents.inputs import FleetView, Observation
from phalanx.agents.masking import MaskInputs
from phalanx.agents.sensing import Sensing, Stance
from phalanx.core.frozen import quick_init
from phalanx.core.geometry import Pose2D, Twist2D, Vec2
from phalanx.core.peers import PeerFlags, PeerState
from phalanx.core.robot import Odometry, RobotStatus

QUICK = (
    Vec2,
    Pose2D,
    Twist2D,
    PeerFlags,
    PeerState,
    Odometry,
    RobotStatus,
    Observation,
    FleetView,
    MaskInputs,
    Sensing,
    Stance,
    StackContext,
    Moment,
    FollowerInput,
)


@pytest.mark.parametrize("cls", QUICK, ids=lambda c: c.__name__)
def test_quick_init_keeps_the_signature_and_stores_every_field(cls: type) -> None:
    fields = dataclasses.fields(cls)
    params = list(inspect.signature(cls).parameters.values())
    assert [p.name for p in params] == [f.name for f in fields]
    assert [p.default for p in params] == [
        inspect.Parameter.empty if f.default is dataclasses.MISSING else f.default for f in fields
    ]
    values = [object() for _ in fields]  # a distinct value per field: none mixed up
    by_position, by_name = (
        cls(*values),
        cls(**{f.name: v for f, v in zip(fields, values, strict=True)}),
    )
    for f, v in zip(fields, values, strict=True):
        assert getattr(by_position, f.name) is v
        assert getattr(by_name, f.name) is v
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(by_position, fields[0].name, None)
    with pytest.raises(TypeError):
        cls(*values, unexpected=1)


def test_defaults_are_the_dataclass_defaults() -> None:
    assert StackContext() == StackContext(is_leader=False, plan="scripted", others_busy=False)
    assert RobotStatus().faults == ()
    assert dataclasses.replace(Pose2D(1.0, 2.0, 3.0), y_m=5.0) == Pose2D(1.0, 5.0, 3.0)
    assert hash(Vec2(1.0, 2.0)) == hash(Vec2(1.0, 2.0))
    with pytest.raises(TypeError):
        Pose2D(1.0, 2.0)  # type: ignore[call-arg]


def test_quick_init_refuses_what_it_does_not_do() -> None:
    @dataclasses.dataclass
    class Mutable:
        a: int

    @dataclasses.dataclass(frozen=True)
    class Factory:
        a: tuple[int, ...] = dataclasses.field(default_factory=tuple)

    @dataclasses.dataclass(frozen=True)
    class Checked:
        a: int

        def __post_init__(self) -> None:
            pass

    for cls in (Mutable, Factory, Checked):
        with pytest.raises(TypeError):
            quick_init(cls)
