"""Frozen dataclasses with the quicker `__init__` (rigbus/records.py): the same signature,
instances equal to the ones dataclasses' own `__init__` builds, still frozen; classes it cannot
give one keep theirs."""

from __future__ import annotations

import dataclasses
import inspect
from dataclasses import InitVar, dataclass, field

import pytest

from controllers.estimation import DriveReading, Estimate, MarkerFrame
from hil.devices import SyncContext
from hil.vision import Picture
from rigbus.protocol import CameraMarker, DriveStatus
from rigbus.records import fast_init, replace_init


def twin(cls: type) -> type:
    """`cls` as dataclasses makes it, with dataclasses' own `__init__`: the same fields, the
    same defaults."""
    spec = [
        (f.name, f.type) if f.default is dataclasses.MISSING else (f.name, f.type, f.default)
        for f in dataclasses.fields(cls)
    ]
    return dataclasses.make_dataclass(cls.__name__, spec, frozen=True)


@pytest.mark.parametrize(
    "cls", [DriveReading, Estimate, MarkerFrame, SyncContext, Picture, DriveStatus, CameraMarker]
)
def test_replaced_inits_keep_the_signature_and_build_the_same_instance(cls: type) -> None:
    own = twin(cls)
    assert cls.__init__.__qualname__ == f"{cls.__qualname__}.__init__"
    assert "__dict__" in cls.__init__.__code__.co_names  # replaced: fills the dict
    assert "__dict__" not in own.__init__.__code__.co_names
    assert inspect.signature(cls) == inspect.signature(own)
    names = [f.name for f in dataclasses.fields(cls)]
    required = [f.name for f in dataclasses.fields(cls) if f.default is dataclasses.MISSING]
    values = {name: float(k + 1) for k, name in enumerate(names)}
    for given in ({n: values[n] for n in required}, values):
        a, b = cls(**given), own(**given)
        assert a.__dict__ == b.__dict__ and list(a.__dict__) == list(b.__dict__)
        assert cls(*given.values()).__dict__ == b.__dict__  # positionally too
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(a, names[0], 0.0)
    with pytest.raises(TypeError):
        cls()


def test_classes_it_cannot_do_keep_their_init() -> None:
    @dataclass
    class Mutable:
        a: int

    @dataclass(frozen=True)
    class Factory:
        a: list = field(default_factory=list)

    @dataclass(frozen=True)
    class Post:
        a: int

        def __post_init__(self) -> None:
            pass

    @dataclass(frozen=True, kw_only=True)
    class KeywordOnly:
        a: int

    @dataclass(frozen=True)
    class WithInitVar:
        a: int
        b: InitVar[int] = 0

    @dataclass(frozen=True, slots=True)
    class Slotted:
        a: int

    @dataclass(frozen=True)
    class Hidden:
        a: int
        b: int = field(default=2, init=False)

    for cls in (Mutable, Factory, Post, KeywordOnly, WithInitVar, Slotted, Hidden, int):
        before = cls.__init__
        assert not replace_init(cls), cls
        assert cls.__init__ is before

    @fast_init
    @dataclass(frozen=True)
    class Plain:
        a: int
        b: tuple = (1, 2)

    assert Plain(1) == Plain(1, (1, 2)) and Plain(1).b is Plain(2).b
    assert (
        repr(Plain(3, b=()))
        == "test_classes_it_cannot_do_keep_their_init.<locals>.Plain(a=3, b=())"
    )
