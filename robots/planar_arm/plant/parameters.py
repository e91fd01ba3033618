"""The planar arm's `[robot]` section (PlanarArmSpec and its tables) and the resolution of its
per-actuator parameters, which the rig, the controller's configuration and the task plan read.

Per-actuator parameters: in `[robot.segment]` and `[robot.cylinder]` a scalar sets every
actuator, a list sets one value per actuator, and a table named by the 1-based actuator index
(`[robot.segment.3]`) overrides that one actuator. Each segment's gas circuit takes its own
cylinder's bore and stroke and is sealed where that piston starts.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

from controllers.curvature import SegmentModel
from hil.schema import Range, Rule, Table, setting
from robots.planar_arm.plant import checks, environment, gripper

if TYPE_CHECKING:
    from hil.scenario import Scenario

NAME = "planar_arm"  # the robot kind

# The thesis's two planar arms [thesis]: free space uses bidirectional
# "rectangular" FEAs (the FeaSegment defaults), confined spaces bidirectional "cylindrical" FEAs.
# [estimate] The cylindrical actuator is rounder and slimmer (16 mm against 20 mm wide): lighter,
# a little stiffer in bending, with less channel volume change per bend angle and a lower
# mechanical limit (1.2 rad: about 20 1/m over 60 mm). A scenario's own values override the set.
PARAMETER_SETS: dict[str, dict[str, dict[str, float]]] = {
    "rectangular": {"segment": {}, "cylinder": {}},
    "cylindrical": {
        "segment": {"mass": 0.02, "k_bend": 0.03, "G_a": 7.0e-7, "theta_max": 1.2},
        "cylinder": {},
    },
}
ACTUATOR_WIDTH = {"rectangular": 0.02, "cylindrical": 0.016}  # backbone width for contact [m]
PER_ACTUATOR = (
    "a value sets every actuator, a list one value per actuator, a table [robot.{table}.N] "
    "actuator N's"
)


TABLES = (
    Table(
        "robot.segment",
        (),
        fmu="FeaSegment",
        checked=False,
        doc=PER_ACTUATOR.format(table="segment"),
        refused=checks.SEGMENT_GEOMETRY,
        refused_why=checks.GEOMETRY_WHY,
    ),
    Table(
        "robot.cylinder",
        (),
        fmu="DriveCylinder",
        checked=False,
        doc=PER_ACTUATOR.format(table="cylinder"),
    ),
    environment.TABLE,
    environment.OBJECT,
    gripper.TABLE,
    Table(
        "robot.gripper.segment",
        (),
        fmu=gripper.SEGMENT_FMU,
        checked=False,
        doc="the finger pair's FeaSegment parameters (its length is robot.gripper's finger_length)",
        starts=gripper.GRIPPER_SEGMENT,
        refused=checks.SEGMENT_GEOMETRY,
        refused_why="set them in robot.gripper.cylinder",
    ),
    Table(
        "robot.gripper.cylinder",
        (),
        fmu=gripper.CYLINDER_FMU,
        checked=False,
        doc="the gripper's drive cylinder's parameters",
    ),
)


@dataclass(frozen=True)
class PlanarArmSpec:
    """The `[robot]` section of a planar arm."""

    kind: str = setting("planar_arm", doc="the robot kind")
    segments: int = setting(
        1,
        "",
        "segments, each with its drive cylinder and drive",
        Range(1, 8, why="a marker each and the gripper's drive after them"),
    )
    base: tuple[float, float, float] = setting(
        (0.0, 0.0, math.pi / 2), "m, m, rad", "the base: x, y, heading"
    )
    model: str = setting(
        "segments",
        doc="the arm's model: segments, one FeaSegment FMU (or robot.segment_fmu) per segment, "
        "each with its own inertia only; body, one multibody ArmBody FMU for every segment (the "
        "inertia between segments: robots/planar_arm/plant/body.py, README)",
        choices=("body", "segments"),
    )
    segment_fmu: str = setting(
        "FeaSegment",
        doc="a segment's FMU: a softhil model, or an .fmu (relative to the file); "
        'another than FeaSegment needs robot.model = "segments"',
    )
    cylinder_fmu: str = setting("DriveCylinder", doc="a drive cylinder's FMU, as segment_fmu")
    segment: dict[str, Any] = setting(
        factory=dict, doc="FeaSegment parameters per actuator (the module docstring)"
    )
    cylinder: dict[str, Any] = setting(
        factory=dict, doc="DriveCylinder parameters per actuator (as robot.segment)"
    )
    segment_decimation: int = setting(
        1, "", "segment FMUs step every N macro steps, N dividing a control period's", Range(1)
    )
    cylinder_decimation: int = setting(
        1, "", "cylinder FMUs step every N macro steps, as segment_decimation", Range(1)
    )
    actuator: str = setting(
        "rectangular",
        doc="the FEA parameter set (PARAMETER_SETS) under the given values",
        choices=tuple(PARAMETER_SETS),
    )
    environment: dict[str, Any] = setting(
        factory=dict, doc="walls and objects: the Environment FMU ([robot.environment])"
    )
    gripper: dict[str, Any] | None = setting(
        None, doc="the finger pair at the tip ([robot.gripper])"
    )

    RULES: ClassVar[tuple[Rule, ...]] = checks.RULES
    TABLES: ClassVar[tuple[Table, ...]] = TABLES


def given(scenario: Scenario, table: str) -> list[dict[str, float]]:
    """The parameters the scenario sets for each actuator of `table` ("segment" or
    "cylinder"), resolved from scalars, lists and per-index tables."""
    return [{k: v for k, (v, _) in p.items()} for p in _given(scenario, table)]


def _given(scenario: Scenario, table: str) -> list[dict[str, tuple[float, str]]]:
    """As `given`, each value with the scenario key it came from."""
    from hil.scenario import fail

    spec: PlanarArmSpec = scenario.robot
    n = spec.segments
    raw: dict[str, Any] = getattr(spec, table)
    preset = PARAMETER_SETS.get(spec.actuator, {}).get(table, {})
    per: list[dict[str, tuple[float, str]]] = [
        {name: (value, "robot.actuator") for name, value in preset.items()} for _ in range(n)
    ]
    overrides: list[tuple[int, str, dict[str, Any]]] = []
    for name, value in raw.items():
        key = f"robot.{table}.{name}"
        if name.isdigit():
            index = int(name)
            if not 1 <= index <= n:
                raise fail(scenario.source, key, f"no {table} {index} (the arm has {n})")
            if not isinstance(value, dict):
                raise fail(scenario.source, key, "must be a table of parameters")
            overrides.append((index, key, value))
        elif isinstance(value, list):
            if len(value) != n:
                raise fail(
                    scenario.source,
                    key,
                    f"has {len(value)} values for {n} {table}s (give one per {table})",
                )
            for i, item in enumerate(value):
                sub = f"{key}[{i}]"
                per[i][name] = (_number(scenario.source, sub, item), sub)
        else:
            per_key = key
            number = _number(scenario.source, key, value)
            for p in per:
                p[name] = (number, per_key)
    for index, key, table_values in overrides:
        for name, value in table_values.items():
            sub = f"{key}.{name}"
            per[index - 1][name] = (_number(scenario.source, sub, value), sub)
    return per


def parameters(scenario: Scenario, table: str) -> list[dict[str, float]]:
    """Every parameter of each actuator: what the scenario sets, else the FMU's default."""

    spec: PlanarArmSpec = scenario.robot
    fmu = spec.segment_fmu if table == "segment" else spec.cylinder_fmu
    defaults: dict[str, float] = {}
    for candidate in ("FeaSegment" if table == "segment" else "DriveCylinder", fmu):
        defaults.update(_defaults(scenario, f"robot.{table}_fmu", candidate))
    return [{**defaults, **own} for own in given(scenario, table)]


def _defaults(scenario: Scenario, key: str, fmu: str) -> dict[str, float]:
    """The start values of the parameters of FMU `fmu` (named in the scenario at `key`)."""
    from hil.scenario import fmu_interface

    return {
        name: port.start
        for name, port in fmu_interface(scenario.source, key, fmu).items()
        if port.causality == "parameter" and port.start is not None
    }


def _segment_model(segment: Mapping[str, float], cylinder: Mapping[str, float]) -> SegmentModel:
    """A segment's static model: its parameters, its cylinder's bore and stroke, its circuit
    sealed where the piston starts."""
    values = {**segment, "bore": cylinder["bore"], "stroke": cylinder["stroke"]}
    return SegmentModel(
        **{
            k: values[k]
            for k in SegmentModel.__dataclass_fields__
            if k not in ("x_seal", "inertia")
        },
        x_seal=cylinder["x_start"],
    )


def _interface(scenario: Scenario, table: str) -> Mapping[str, Any]:
    from hil.scenario import fmu_interface

    fmu = scenario.robot.segment_fmu if table == "segment" else scenario.robot.cylinder_fmu
    return fmu_interface(scenario.source, f"robot.{table}_fmu", fmu)


def _number(file: str, key: str, value: Any) -> float:
    from hil.scenario import fail

    if isinstance(value, bool) or not isinstance(value, int | float):
        raise fail(file, key, f"must be a number, got {value!r}")
    if not math.isfinite(value):
        raise fail(file, key, f"must be finite, got {value!r}")
    return float(value)
