"""Robot kinds as plug-ins, chosen by the scenario's `[robot] kind` the way python-can chooses an
interface by name (rigbus/robots.py; README, "Robots, devices, protocol").

A robot kind owns, for the plant side: the schema and checks of its `[robot]` section (per
actuator parameters), its FMUs and device nodes and their connections (`build` -> `Rig`), the
markers the camera sees, the signals it records, plots and animates, the frames it puts on the
bus (for the bus load) and its task metrics; and it names its controller side
(`controller_config`).
The plant loop, the master, the bus and the recorders know no robot.

Kinds are found through `rigbus.robots`, where one entry registers both sides of a robot
(softhil's own in `robots/<kind>/`, another package's through the `softhil.robots` entry-point
group), so another package can add one without editing softhil.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from hil.cosim import Connection, FmuParticipant, Participant
from hil.devices import DeviceNode
from hil.errors import HilError
from rigbus.robots import known, plant_side

if TYPE_CHECKING:
    from hil.scenario import Scenario
    from hil.vision import Camera
    from rigbus.protocol import Protocol as CanProtocol


@dataclass(frozen=True)
class SignalSpec:
    """One recorded column: where its value comes from at each SYNC, its unit, what it is.

    `source` is a master value ("segment1.kappa"); `frame` instead names a signal of a frame the
    controller sends, (DBC kind, index, signal), recorded as the controller reported it (index
    None for a kind without one, as TaskState: `rigbus.protocol.frame_key`)."""

    column: str
    unit: str
    description: str
    source: str | None = None
    frame: tuple[str, int | None, str] | None = None


@dataclass(frozen=True)
class PlotSpec:
    """One PNG: a panel per group of columns (one per actuator), each line a column."""

    name: str
    ylabel: str
    panels: tuple[str, ...]  # panel titles
    lines: tuple[
        tuple[str, str, float, dict[str, Any]], ...
    ]  # (column template, label, scale, style)


@dataclass
class Rig:
    """Everything the master steps and everything on the bus on the plant's side."""

    participants: list[Participant]
    connections: list[Connection]
    nodes: list[DeviceNode]  # in the order they act and send within a phase
    signals: list[SignalSpec]
    plots: list[PlotSpec] = field(default_factory=list)
    parameters: dict[str, Mapping[str, float]] = field(default_factory=dict)  # per participant
    # figures beyond the line plots: (name, draw(signals, path)) writing `<name>.png`
    figures: list[tuple[str, Callable[[Mapping[str, Any], Path], None]]] = field(
        default_factory=list
    )
    # the run's animation, where the kind has one: (name, animate(signals, path, fmt)) writing
    # `<name>.<fmt>` (fmt "gif" or "mp4", hil.animation) for `hil run --animate`
    animation: tuple[str, Callable[[Mapping[str, Any], Path, str], None]] | None = None

    def close(self) -> None:
        for participant in self.participants:
            if isinstance(participant, FmuParticipant):
                participant.close()


class RobotKind(Protocol):
    """What a robot kind provides; see the module docstring."""

    name: str
    # the dataclass of its [robot] section: keys declared with hil.schema.setting, rules
    # between keys in RULES, its tables in TABLES; `check` holds the checks that are code
    spec_class: type

    def check(self, scenario: Scenario) -> None: ...
    def ports(self, scenario: Scenario) -> dict[str, tuple[set[str], set[str]]]: ...
    def reach(self, scenario: Scenario) -> float: ...
    def build(self, scenario: Scenario) -> Rig: ...
    def controller_config(self, scenario: Scenario) -> Any: ...
    def frame_rates(self, scenario: Scenario, protocol: CanProtocol) -> dict[str, float]: ...
    def task_metrics(self, scenario: Scenario, signals: Mapping[str, Any]) -> dict[str, Any]: ...


def robot_kind(name: str) -> RobotKind:
    """The plant side of the robot kind registered under `name`; HilError naming the known kinds
    otherwise."""
    try:
        return plant_side(name)  # type: ignore[no-any-return]
    except ValueError as exc:
        raise HilError(str(exc)) from None


def known_kinds() -> list[str]:
    return known()


def fmu_ref(source: str, fmu: str) -> str:
    """An FMU named in a scenario: a softhil model name, or an .fmu path relative to the file."""
    if not fmu.endswith(".fmu"):
        return fmu
    path = Path(fmu)
    return str(path if path.is_absolute() else Path(source).parent / path)


def scenario_camera(scenario: Scenario) -> Camera:
    """The scenario's camera model: its imperfections, its rate, the plant's step, and its own
    random stream seeded by the scenario's seed (apart from every other draw of the run)."""
    from hil.vision import Camera

    return Camera(
        scenario.camera.effects(),
        np.random.default_rng(scenario.seed),
        1.0 / scenario.camera.rate,
        scenario.timing.step,
    )


def build_rig(scenario: Scenario) -> Rig:
    """The rig of the scenario's robot kind."""
    return robot_kind(scenario.robot.kind).build(scenario)
