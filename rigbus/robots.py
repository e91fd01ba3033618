"""Robot kinds as plug-ins: one entry registers both sides of a robot.

A robot kind lives in one folder (softhil's own in `robots/<kind>/`): its plant side (a
`RobotKind` object that `hil` builds the rig from) and its controller side (a module with
`config_class`, `make_estimator(config)`, `make_controller(config, protocol)`, `expected(config)`
and `readings(status)`, which the controller node runs). `RobotEntry` names both by import path,
so that importing an entry imports neither side: the controller program never loads plant code,
and the plant loads the controller side only where it configures or runs one.

softhil's kinds are `BUILT_IN`; another package adds one through the `softhil.robots`
entry-point group, whose object is a `RobotEntry`, the way python-can finds an interface.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from importlib.metadata import entry_points
from types import ModuleType
from typing import Any, Protocol

GROUP = "softhil.robots"


@dataclass(frozen=True)
class RobotEntry:
    """Where robot kind `name` keeps its two sides: `plant` is "module:attribute" of its
    RobotKind, `controller` the module of its controller side."""

    name: str
    plant: str
    controller: str


class RobotConfig(Protocol):
    """What every robot kind's controller configuration has (the node and the plant's tools
    read these; the rest is the robot's own)."""

    @property
    def robot(self) -> str: ...
    @property
    def policy(self) -> str: ...
    @property
    def control_period(self) -> float: ...
    @property
    def cycles(self) -> int: ...
    @property
    def timeout(self) -> float: ...
    def to_json(self) -> str: ...


BUILT_IN = {
    entry.name: entry
    for entry in (
        RobotEntry("planar_arm", "robots.planar_arm.plant:ROBOT", "robots.planar_arm.controller"),
        RobotEntry("fish", "robots.fish.plant:ROBOT", "robots.fish.controller"),
        RobotEntry(
            "spatial_arm", "robots.spatial_arm.plant:ROBOT", "robots.spatial_arm.controller"
        ),
    )
}


def known() -> list[str]:
    """Every robot kind's name: built in and registered."""
    return sorted({*BUILT_IN, *(ep.name for ep in entry_points(group=GROUP))})


def robot_entry(name: str) -> RobotEntry:
    """The entry of robot kind `name`; ValueError naming the known kinds otherwise."""
    found = BUILT_IN.get(name)
    if found is None:
        for ep in entry_points(group=GROUP):
            if ep.name == name:
                found = ep.load()
                break
    if not isinstance(found, RobotEntry):
        raise ValueError(f"unknown robot kind {name!r} (known: {', '.join(known())})")
    return found


def controller_side(name: str) -> ModuleType:
    """The controller-side module of robot kind `name`."""
    return importlib.import_module(robot_entry(name).controller)


def plant_side(name: str) -> Any:
    """The plant side (its RobotKind) of robot kind `name`."""
    module, _, attribute = robot_entry(name).plant.partition(":")
    return getattr(importlib.import_module(module), attribute)
