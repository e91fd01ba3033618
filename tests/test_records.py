"""The records built at every SYNC (the frames, the drives' readings, the estimates, the camera's
pictures, the devices' SYNC contexts) are plain frozen, slotted dataclasses: dataclasses' own
`__init__` (the signature and defaults declared), no instance dict, immutable, equal only to a
record of their own type."""

from __future__ import annotations

import dataclasses
import inspect

import pytest

from controllers.estimation import DriveReading, Estimate, MarkerFrame
from hil.devices import SyncContext
from hil.vision import Picture
from rigbus.protocol import _REGISTRY, ControllerState, DriveCommand

RECORDS = [DriveReading, Estimate, MarkerFrame, SyncContext, Picture]
FRAMES = [ftype.cls for ftype in _REGISTRY.values()]


@pytest.mark.parametrize("cls", RECORDS + FRAMES, ids=lambda cls: cls.__name__)
def test_records_are_frozen_slotted_dataclasses(cls: type) -> None:
    assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen  # type: ignore[attr-defined]
    fields = dataclasses.fields(cls)
    names = [f.name for f in fields]
    assert cls.__slots__ == tuple(names)  # type: ignore[attr-defined]
    assert list(inspect.signature(cls).parameters) == names
    required = [f.name for f in fields if f.default is dataclasses.MISSING]
    values = {name: float(k + 1) for k, name in enumerate(names)}
    record = cls(**{name: values[name] for name in required})
    for f in fields:  # the declared defaults, as declared
        expected = values[f.name] if f.default is dataclasses.MISSING else f.default
        assert getattr(record, f.name) is expected or getattr(record, f.name) == expected
    full = cls(**values)
    assert cls(*values.values()) == full and [getattr(full, n) for n in names] == list(
        values.values()
    )
    assert not hasattr(full, "__dict__")
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(full, names[0], 0.0)
    with pytest.raises((dataclasses.FrozenInstanceError, AttributeError, TypeError)):
        full.extra = 1  # type: ignore[attr-defined]
    with pytest.raises(TypeError):
        cls()


def test_frames_are_equal_only_to_frames_of_their_own_type() -> None:
    """What a NamedTuple frame would not give: a command is not a controller state with the
    same values, nor a tuple; and `dataclasses.replace` makes a changed copy."""
    command = DriveCommand(1, 0.0, False, 3)
    assert command != ControllerState(1, 0.0, 0.0, 3)
    assert command != (1, 0.0, False, 3)
    assert dataclasses.replace(command, counter=4) == DriveCommand(1, 0.0, False, 4)
    assert dataclasses.asdict(command) == {
        "node": 1,
        "piston_setpoint": 0.0,
        "enable": False,
        "counter": 3,
    }
