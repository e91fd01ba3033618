"""The planar arm (PHYSICS.md sections 1-3, 6): per segment a DriveCylinder FMU, a FeaSegment FMU
and a drive-firmware node; one camera seeing a marker at the base and at every segment end.

Per-actuator parameters: in `[robot.segment]` and `[robot.cylinder]` a scalar sets every
actuator, a list sets one value per actuator, and a table named by the 1-based actuator index
(`[robot.segment.3]`) overrides that one actuator. Each segment's gas circuit takes its own
cylinder's bore and stroke and is sealed where that piston starts.

The module stays above the house's 600 lines (about 930): the `[robot]` section, the rig, the
controller's configuration and the task plan all read one per-actuator parameter resolution
(`_given`, `parameters`) and are one robot kind; its scenario checks are in checks.py.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from controllers import kinematics
from controllers.config import CameraTiming
from controllers.curvature import PiGains, SegmentModel
from controllers.estimation import BendModel, CameraNoise
from controllers.loop_design import effective_delay, estimator_delay, outer_loop_gains
from hil.cosim import Connection, FmuParticipant, Participant
from hil.devices import HEARTBEAT_PERIOD, CameraNode, DriveNode
from hil.rig import PlotSpec, Rig, SignalSpec, fmu_ref, scenario_camera
from hil.schema import Range, Rule, Table, setting
from hil.vision import exposure_delay_bound
from rigbus.protocol import Protocol
from robots.planar_arm.controller.config import ControllerConfig, GripperConfig
from robots.planar_arm.controller.tasks import TASK_KINDS, TaskPlan, draw_paths, draw_targets
from robots.planar_arm.plant import checks, environment, gripper
from robots.planar_arm.plant.checks import IK_RANGE_SHARE

if TYPE_CHECKING:
    from hil.scenario import Scenario

TASK_STREAM = 0x7A5C  # the task's random stream, apart from the camera's (seeded by the seed alone)
DRIVE_SPEED_SHARE = 0.5  # of the drive's no-load speed that curvature moves may ask for
# the [task] keys the controller's plan takes as they are
PLAN_KEYS = (
    "tolerance",
    "settle_time",
    "max_time",
    "speed",
    "acceleration",
    "task_gain",
    "centreline",
    "clearance",
    "grasp_time",
)

_LAYOUTS: dict[str, tuple[tuple[float, float], tuple[float, float]]] = {}  # grasp_layout's

# The thesis's two planar arms [thesis, PHYSICS.md section 6]: free space uses bidirectional
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
    segment_fmu: str = setting(
        "FeaSegment", doc="a segment's FMU: a softhil model, or an .fmu (relative to the file)"
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


PER_SEGMENT: tuple[tuple[str, str, str], ...] = (
    ("kappa_ref", "1/m", "curvature reference, as the controller reported it"),
    ("kappa_est", "1/m", "controller's curvature estimate, as it reported it"),
    ("kappa", "1/m", "true curvature"),
    ("theta", "rad", "true bend angle"),
    ("p_a", "Pa", "gauge pressure of side a"),
    ("p_b", "Pa", "gauge pressure of side b"),
    ("x", "m", "piston position"),
    ("x_ref", "m", "piston setpoint the drive firmware applies"),
    ("v", "m/s", "piston velocity"),
    ("i_motor", "A", "drive motor current"),
    ("fault", "", "drive fault bits (DriveStatus.fault)"),
)
TASK_SIGNALS: tuple[tuple[str, str, str], ...] = (
    ("target_index", "", "target (point-to-point) or path (path task) pursued, 0 first"),
    (
        "phase",
        "",
        "task phase: 0 idle, 1 moving, 2 settling, 3 settled, 4 done, 5 tracking, 6 grasping, "
        "7 releasing",
    ),
    ("target_x", "m", "task-space reference point x, as the controller reported it"),
    ("target_y", "m", "task-space reference point y, as the controller reported it"),
)
_SOURCES = {
    "kappa": "segment{n}.kappa",
    "theta": "segment{n}.theta",
    "p_a": "segment{n}.p_a",
    "p_b": "segment{n}.p_b",
    "x": "cylinder{n}.x",
    "x_ref": "drive{n}.x_ref",
    "v": "cylinder{n}.v",
    "i_motor": "cylinder{n}.i_motor",
    "fault": "drive{n}.fault",
}


class PlanarArm:
    name = "planar_arm"
    spec_class = PlanarArmSpec

    # ------------------------------------------------------------------ parameters

    def given(self, scenario: Scenario, table: str) -> list[dict[str, float]]:
        """The parameters the scenario sets for each actuator of `table` ("segment" or
        "cylinder"), resolved from scalars, lists and per-index tables."""
        return [{k: v for k, (v, _) in p.items()} for p in self._given(scenario, table)]

    def _given(self, scenario: Scenario, table: str) -> list[dict[str, tuple[float, str]]]:
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

    def parameters(self, scenario: Scenario, table: str) -> list[dict[str, float]]:
        """Every parameter of each actuator: what the scenario sets, else the FMU's default."""

        spec: PlanarArmSpec = scenario.robot
        fmu = spec.segment_fmu if table == "segment" else spec.cylinder_fmu
        defaults: dict[str, float] = {}
        for candidate in ("FeaSegment" if table == "segment" else "DriveCylinder", fmu):
            defaults.update(_defaults(scenario, f"robot.{table}_fmu", candidate))
        return [{**defaults, **given} for given in self.given(scenario, table)]

    # ------------------------------------------------------------------ checks

    def check(self, scenario: Scenario) -> None:
        """The arm's scenario checks that are code (robots.planar_arm.plant.checks)."""
        checks.check(self, scenario)

    def environment_parameters(self, s: Scenario) -> dict[str, float]:
        """The Environment FMU's parameters: `[robot.environment]`, the arm's segments, the
        gripper's fingers, and the objects the task places."""
        values = environment.parameters(
            s, self.parameters(s, "segment"), ACTUATOR_WIDTH[s.robot.actuator], self._placed(s)
        )
        if gripper.present(s):
            values.update(gripper.environment_parameters(s))
            # the implicit coupling predicts the fingers with their mobility too
            d_bend = gripper.segment_values(s)["d_bend"]
            values["arm_mobility"] = max(values["arm_mobility"], 1.0 / max(d_bend, 1e-12))
        return values

    def _placed(self, s: Scenario) -> dict[int, tuple[float, float]]:
        """Objects the task places: a grasp task's object, from the seed unless given."""
        if s.task.kind != "grasp":
            return {}
        return {1: self.grasp_layout(s)[0]}

    def ports(self, scenario: Scenario) -> dict[str, tuple[set[str], set[str]]]:
        """What each participant offers: (outputs, inputs), for the scenario's connections."""
        from hil.scenario import fmu_interface

        r: PlanarArmSpec = scenario.robot
        interfaces = {
            "segment": fmu_interface(scenario.source, "robot.segment_fmu", r.segment_fmu),
            "cylinder": fmu_interface(scenario.source, "robot.cylinder_fmu", r.cylinder_fmu),
        }
        ports: dict[str, tuple[set[str], set[str]]] = {
            "camera": (set(), set(self.camera_inputs(scenario)))
        }
        for i in range(1, r.segments + 1):
            for kind, interface in interfaces.items():
                ports[f"{kind}{i}"] = (
                    {n for n, v in interface.items() if v.causality == "output"},
                    {n for n, v in interface.items() if v.causality == "input"},
                )
            ports[f"drive{i}"] = ({"x_ref", "enable", "fault"}, {"x", "p_a", "p_b", "servo_fault"})
        if gripper.present(scenario):
            g = gripper.node(scenario)
            for kind, fmu in (("gripper", gripper.SEGMENT_FMU), (f"cylinder{g}", "DriveCylinder")):
                interface = fmu_interface(scenario.source, "robot.gripper", fmu)
                ports[kind] = (
                    {n for n, v in interface.items() if v.causality == "output"},
                    {n for n, v in interface.items() if v.causality == "input"},
                )
            ports[f"drive{g}"] = ({"x_ref", "enable", "fault"}, {"x", "p_a", "p_b", "servo_fault"})
        if environment.present(scenario):
            interface = fmu_interface(scenario.source, "robot.environment", environment.FMU)
            ports["environment"] = (
                {n for n, v in interface.items() if v.causality == "output"},
                {n for n, v in interface.items() if v.causality == "input"},
            )
        return ports

    def start_pistons(self, scenario: Scenario) -> list[float]:
        """Where each piston starts [m]: at the cylinder's x_start, where the circuit was sealed
        with the segment straight, unless the segment starts bent (theta_start): then at the
        piston position whose static equilibrium is that bend, so that the arm starts at rest
        in its bent configuration instead of springing back."""
        pistons = []
        for model, segment, cylinder in zip(
            self.segment_models(scenario),
            self.parameters(scenario, "segment"),
            self.parameters(scenario, "cylinder"),
            strict=True,
        ):
            theta = segment.get("theta_start", 0.0)
            if theta == 0.0:
                pistons.append(cylinder["x_start"])
            else:
                pistons.append(model.piston_for_curvature(theta / segment["length"]))
        return pistons

    def camera_inputs(self, scenario: Scenario) -> list[str]:
        """What the camera sees: each segment's curvature (the arm's markers), then each
        object's position (its marker, ids segments + 1 ...)."""
        names = [f"kappa_{n}" for n in range(1, scenario.robot.segments + 1)]
        if environment.present(scenario):
            for o in range(1, len(scenario.robot.environment.get("objects", [])) + 1):
                names += [f"object_x_{o}", f"object_y_{o}"]
        return names

    def gripper_cylinder(self, scenario: Scenario) -> dict[str, float]:
        """Every parameter of the gripper's drive cylinder."""
        defaults = _defaults(scenario, "robot.gripper.cylinder", gripper.CYLINDER_FMU)
        return {**defaults, **gripper.table(scenario, "cylinder")}

    def gripper_model(self, scenario: Scenario) -> SegmentModel:
        """The finger pair's static model (as the arm's segment_models)."""
        segment = {
            **_defaults(scenario, "robot.gripper.segment", gripper.SEGMENT_FMU),
            **gripper.segment_values(scenario),
        }
        return _segment_model(segment, self.gripper_cylinder(scenario))

    def grasp_layout(self, scenario: Scenario) -> tuple[tuple[float, float], tuple[float, float]]:
        """Where a grasp task's object starts and where it is to be placed [m]: the task's
        `pick` and `place`, else drawn from the seed within the reachable workspace."""
        from hil.scenario import fail
        from robots.planar_arm.controller.grasp import draw_grasp_task

        task = scenario.task
        if task.pick is not None and task.place is not None:
            return task.pick, task.place
        key = repr((scenario.seed, task, scenario.robot))  # the draw plans: ~1 s, asked often
        if key in _LAYOUTS:
            return _LAYOUTS[key]
        lower, upper, _ = self.curvature_limits(scenario)
        mid, half = 0.5 * (lower + upper), 0.5 * (upper - lower) * IK_RANGE_SHARE
        lengths = [p["length"] for p in self.parameters(scenario, "segment")]
        rng = np.random.default_rng([scenario.seed, TASK_STREAM])
        start = [
            p.get("theta_start", 0.0) / p["length"] for p in self.parameters(scenario, "segment")
        ]
        radius = self.grasp_object(scenario)["radius"]
        try:
            pick, place = draw_grasp_task(
                rng,
                lengths,
                scenario.robot.base,
                mid - half,
                mid + half,
                gripper.geometry(scenario),
                radius,
                start,
            )
        except ValueError as exc:
            raise fail(
                scenario.source,
                "task",
                f"{exc} for an object of radius {radius:g} m "
                "(robot.environment.objects[0].radius): give task.pick and task.place, "
                "or a smaller object",
            ) from None
        layout = (task.pick or pick, task.place or place)
        if len(_LAYOUTS) >= 64:
            _LAYOUTS.clear()
        _LAYOUTS[key] = layout
        return layout

    def grasp_object(self, scenario: Scenario) -> dict[str, float]:
        """The grasp task's object (the first of `[robot.environment] objects`): its keys."""
        from hil.scenario import fail

        items = environment.objects(scenario) if environment.present(scenario) else []
        if not items:
            raise fail(
                scenario.source, "robot.environment.objects", "a grasp task needs its object"
            )
        return {k: v for k, v in items[0].items() if v is not None}

    def reach(self, scenario: Scenario) -> float:
        """Farthest a marker can be from the base [m]: the arm's length."""
        return sum(p["length"] for p in self.parameters(scenario, "segment"))

    # ------------------------------------------------------------------ the rig

    def build(self, scenario: Scenario) -> Rig:
        """For each n: drive n's firmware sets cylinder n's setpoint and watches its position
        and segment n's pressures; cylinder n moves segment n's piston and feels its pressures;
        the camera sees every segment's curvature. Scenario connections replace defaults that
        drive the same input, and add the others."""
        from hil.fmu.slave import FmuSlave

        r: PlanarArmSpec = scenario.robot
        protocol = Protocol()
        segments_given = self.given(scenario, "segment")
        cylinders_given = self.given(scenario, "cylinder")
        segments = self.parameters(scenario, "segment")
        cylinders = self.parameters(scenario, "cylinder")
        segment_names = {
            n for n, p in _interface(scenario, "segment").items() if p.causality == "parameter"
        }
        timeout_ticks = round(scenario.safety.command_timeout / scenario.timing.step)
        pistons = self.start_pistons(scenario)
        drives = [
            DriveNode(
                n,
                pistons[n - 1],
                pistons[n - 1],
                scenario.safety.max_pressure,
                timeout_ticks,
                position_range=protocol.signal_range("DriveStatus1", "piston_position"),
                pressure_range=protocol.signal_range("DriveStatus1", "p_a"),
                # the firmware holds its outputs between SYNCs: stepping it at SYNC ticks only
                # changes nothing and keeps the master's C kernel running between SYNCs
                decimation=scenario.control_ticks,
            )
            for n in range(1, r.segments + 1)
        ]
        if gripper.present(scenario):
            g = gripper.node(scenario)
            x_start = self.gripper_cylinder(scenario)["x_start"]
            drives.append(
                DriveNode(
                    g,
                    x_start,
                    x_start,
                    scenario.safety.max_pressure,
                    timeout_ticks,
                    position_range=protocol.signal_range(f"DriveStatus{g}", "piston_position"),
                    pressure_range=protocol.signal_range(f"DriveStatus{g}", "p_a"),
                    decimation=scenario.control_ticks,
                )
            )
        lengths = [p["length"] for p in segments]
        base = r.base
        n_arm = r.segments

        def marker_model(values: Sequence[float]) -> np.ndarray:
            """The arm's markers (base, every segment end), then each object's (its centre)."""
            arm = kinematics.markers(values[:n_arm], lengths, base)
            if len(values) == n_arm:
                return arm
            objects = np.reshape(values[n_arm:], (-1, 2))
            return np.vstack([arm, objects])

        camera = CameraNode(
            self.camera_inputs(scenario),
            marker_model,
            scenario.latency_ticks,
            scenario_camera(scenario),
        )
        fmus: list[FmuParticipant] = []
        connections: dict[str, Connection] = {}
        parameters: dict[str, Mapping[str, float]] = {}
        try:
            for n in range(1, r.segments + 1):
                cylinder_values = dict(cylinders_given[n - 1])
                if pistons[n - 1] != cylinders[n - 1]["x_start"]:
                    cylinder_values["x_start"] = pistons[n - 1]  # a segment that starts bent
                # every FMU stays in initialisation mode until the master has passed the
                # connected start values along (Algorithm._initialise)
                cylinder = FmuSlave(
                    fmu_ref(scenario.source, r.cylinder_fmu),
                    f"cylinder{n}",
                    cylinder_values,
                    exit_initialization=False,
                )
                fmus.append(FmuParticipant(cylinder, r.cylinder_decimation))
                # the segment's gas circuit includes the cylinder: same bore and stroke, sealed
                # where the piston starts
                geometry = {
                    "bore": cylinders[n - 1]["bore"],
                    "stroke": cylinders[n - 1]["stroke"],
                    "x_seal": cylinders[n - 1]["x_start"],
                }
                segment_values = {
                    **{k: v for k, v in geometry.items() if k in segment_names},
                    **segments_given[n - 1],
                }
                segment = FmuSlave(
                    fmu_ref(scenario.source, r.segment_fmu),
                    f"segment{n}",
                    segment_values,
                    exit_initialization=False,
                )
                fmus.append(FmuParticipant(segment, r.segment_decimation))
                parameters[f"cylinder{n}"] = cylinders[n - 1]
                parameters[f"segment{n}"] = {**segments[n - 1], **segment_values}
                for source, target in (
                    *gripper.drive_connections(n, f"segment{n}"),
                    (f"segment{n}.kappa", f"camera.kappa_{n}"),
                ):
                    connections[target] = Connection(source, target)
            if gripper.present(scenario):
                g = gripper.node(scenario)
                cylinder_values = gripper.table(scenario, "cylinder")
                cylinder = FmuSlave(
                    gripper.CYLINDER_FMU, f"cylinder{g}", cylinder_values, exit_initialization=False
                )
                fmus.append(FmuParticipant(cylinder, r.cylinder_decimation))
                full = self.gripper_cylinder(scenario)
                finger_values = {
                    **gripper.segment_values(scenario),
                    "bore": full["bore"],
                    "stroke": full["stroke"],
                    "x_seal": full["x_start"],
                }
                fingers = FmuSlave(
                    gripper.SEGMENT_FMU, "gripper", finger_values, exit_initialization=False
                )
                fmus.append(FmuParticipant(fingers, r.segment_decimation))
                parameters[f"cylinder{g}"] = full
                parameters["gripper"] = finger_values
                for source, target in gripper.connections(scenario):
                    connections[target] = Connection(source, target)
            if environment.present(scenario):
                world_values = self.environment_parameters(scenario)
                world = FmuSlave(
                    environment.FMU, "environment", world_values, exit_initialization=False
                )
                fmus.append(FmuParticipant(world, 1))
                parameters["environment"] = world_values
                for source, target in environment.connections(r.segments):
                    connections[target] = Connection(source, target)
                for name in self.camera_inputs(scenario)[r.segments :]:
                    # object_x_1 ...: the camera sees each object's marker
                    connections[f"camera.{name}"] = Connection(
                        f"environment.{name}", f"camera.{name}"
                    )
        except BaseException:
            for participant in fmus:
                participant.close()
            raise
        for c in scenario.connections:
            connections[c.target] = Connection(c.source, c.target, c.gain, c.offset)
        participants: list[Participant] = [*fmus, *drives, camera]
        figures = []
        if scenario.task.kind in TASK_KINDS:
            from robots.planar_arm.plant.tasks import draw_arm

            figures.append(("arm", lambda signals, path: draw_arm(self, scenario, signals, path)))

        def animate(signals: Mapping[str, Any], path: Path, fmt: str) -> None:
            from robots.planar_arm.plant.animation import animate_arm

            animate_arm(self, scenario, signals, path, fmt)

        return Rig(
            participants,
            list(connections.values()),
            [*drives, camera],
            self.signals(scenario),
            self.plots(scenario),
            parameters,
            figures,
            animation=("arm", animate),
        )

    def signals(self, scenario: Scenario) -> list[SignalSpec]:
        specs = []
        for n in range(1, scenario.robot.segments + 1):
            for name, unit, description in PER_SEGMENT:
                column = f"{name}_{n}"
                text = f"segment {n}: {description}"
                if name in ("kappa_ref", "kappa_est"):
                    specs.append(SignalSpec(column, unit, text, frame=("ControllerState", n, name)))
                else:
                    specs.append(SignalSpec(column, unit, text, source=_SOURCES[name].format(n=n)))
        if gripper.present(scenario):
            g = gripper.node(scenario)
            for name, unit, text, source in (
                ("gripper_theta", "rad", "fingers' bend angle (positive closes)", "gripper.theta"),
                ("gripper_p_a", "Pa", "fingers' side a gauge pressure", "gripper.p_a"),
                ("gripper_p_b", "Pa", "fingers' side b gauge pressure", "gripper.p_b"),
                ("gripper_x", "m", "gripper drive's piston position", f"cylinder{g}.x"),
                ("gripper_x_ref", "m", "gripper drive's piston setpoint", f"drive{g}.x_ref"),
                (
                    "finger_force_left",
                    "N",
                    "left finger's contact force",
                    "environment.finger_force_left",
                ),
                (
                    "finger_force_right",
                    "N",
                    "right finger's contact force",
                    "environment.finger_force_right",
                ),
            ):
                specs.append(SignalSpec(name, unit, text, source=source))
        if environment.present(scenario):
            specs += environment.signals(scenario)
        if scenario.task.kind in TASK_KINDS:
            for name, unit, text in TASK_SIGNALS:
                specs.append(SignalSpec(name, unit, text, frame=("TaskState", None, name)))
        return specs

    def plots(self, scenario: Scenario) -> list[PlotSpec]:
        panels = tuple(f"segment {n}" for n in range(1, scenario.robot.segments + 1))
        return [
            PlotSpec(
                "curvature",
                "curvature [1/m]",
                panels,
                (
                    ("kappa_ref_{n}", "reference", 1.0, {"color": "black", "linestyle": "--"}),
                    ("kappa_est_{n}", "estimate (controller)", 1.0, {"color": "tab:orange"}),
                    ("kappa_{n}", "true", 1.0, {"color": "tab:blue", "alpha": 0.8}),
                ),
            ),
            PlotSpec(
                "pressures",
                "gauge pressure [kPa]",
                panels,
                (
                    ("p_a_{n}", "side a", 1e-3, {"color": "tab:red"}),
                    ("p_b_{n}", "side b", 1e-3, {"color": "tab:green"}),
                ),
            ),
            PlotSpec(
                "piston",
                "piston [mm]",
                panels,
                (
                    ("x_ref_{n}", "setpoint", 1e3, {"color": "black", "linestyle": "--"}),
                    ("x_{n}", "position", 1e3, {"color": "tab:purple"}),
                ),
            ),
        ]

    def frame_rates(self, scenario: Scenario, protocol: Protocol) -> dict[str, float]:
        per_period = 1.0 / scenario.timing.control_period
        rates: dict[str, float] = {"SYNC": per_period}
        for n in range(1, scenario.robot.segments + 1):
            rates[f"DriveStatus{n}"] = per_period
            rates[f"DriveCommand{n}"] = per_period
            rates[f"ControllerState{n}"] = per_period
            rates[f"Heartbeat{n}"] = 1.0 / HEARTBEAT_PERIOD
        if scenario.task.kind in TASK_KINDS:
            rates["TaskState"] = per_period
        if gripper.present(scenario):
            g = gripper.node(scenario)
            rates[f"DriveStatus{g}"] = per_period
            rates[f"DriveCommand{g}"] = per_period
            rates[f"Heartbeat{g}"] = 1.0 / HEARTBEAT_PERIOD
        rates["CameraFrame"] = scenario.camera.rate
        for m in range(self.markers(scenario)):
            rates[f"CameraMarker{m}"] = scenario.camera.rate
        return rates

    # ------------------------------------------------------------------ the controller side

    def segment_models(self, scenario: Scenario) -> list[SegmentModel]:
        models = []
        for segment, cylinder in zip(
            self.parameters(scenario, "segment"), self.parameters(scenario, "cylinder"), strict=True
        ):
            models.append(_segment_model(segment, cylinder))
        return models

    def controller_config(self, scenario: Scenario) -> ControllerConfig:
        """What the controller is told: geometry, period, task, gains (designed unless given)."""
        c = scenario.controller
        models = self.segment_models(scenario)
        segments = self.parameters(scenario, "segment")
        gains = []
        delay = effective_delay(
            estimator_delay(c.estimator, scenario.timing.control_period, c.latency_compensation),
            scenario.timing.control_period,
        )
        for model in models:
            # the design of `hil tune`: a pole-cancelling PI at the scenario's crossover, or
            # lower where the estimator's effective delay leaves less than 60 deg of phase
            designed = outer_loop_gains(model, delay, max_crossover_hz=c.crossover)
            gains.append(
                PiGains(
                    Kp=c.kp if c.kp is not None else designed.Kp,
                    Ki=c.ki if c.ki is not None else designed.Ki,
                )
            )
        return ControllerConfig(
            robot=self.name,
            lengths=tuple(m.length for m in models),
            base=scenario.robot.base,
            control_period=scenario.timing.control_period,
            cycles=scenario.cycles,
            x_mid=tuple(m.x_seal for m in models),
            x_min=tuple(0.0 for _ in models),
            x_max=tuple(m.stroke for m in models),
            gains=tuple(gains),
            feedforward=tuple(1.0 / m.static_gain() if c.feedforward else 0.0 for m in models),
            profile=scenario.task.profile(),
            plan=self.task_plan(scenario),
            policy=c.policy,
            timeout=c.timeout,
            bends=tuple(
                BendModel(
                    length=p["length"],
                    inertia=p["mass"] * p["length"] ** 2 / 20.0,
                    k_bend=p["k_bend"],
                    d_bend=p["d_bend"],
                    G_a=p["G_a"],
                    theta_max=p["theta_max"],
                    vacuum_factor=p.get("vacuum_factor", 1.0),
                    p_collapse=p.get("p_collapse", 1e4),
                )
                for p in segments
            ),
            camera=CameraNoise(
                noise=scenario.camera.noise,
                dropout=scenario.camera.dropout,
                outlier_rate=scenario.camera.outlier_rate,
                outlier_distance=scenario.camera.outlier_distance,
                rate=scenario.camera.rate,
                latency=scenario.camera.latency,
            ),
            estimator=c.estimator,
            latency_compensation=c.latency_compensation,
            torque_std=c.torque_std,
            camera_timing=CameraTiming(
                period_ticks=scenario.camera_ticks,
                latency_ticks=scenario.latency_ticks,
                control_ticks=scenario.control_ticks,
                delay_ticks=exposure_delay_bound(
                    scenario.camera.jitter, scenario.camera_ticks, scenario.timing.step
                ),
                markers=self.markers(scenario),
            ),
            objects=self.markers(scenario) - scenario.robot.segments - 1,
            gripper=self.gripper_config(scenario),
        )

    def markers(self, scenario: Scenario) -> int:
        """Markers the camera reports: the base, each segment end, each object."""
        return (
            scenario.robot.segments
            + 1
            + len(self.camera_inputs(scenario)[scenario.robot.segments :]) // 2
        )

    def gripper_config(self, scenario: Scenario) -> GripperConfig | None:
        """What the controller knows of the gripper: its drive, the pistons that open and close
        it (from the finger pair's static model) and its geometry."""
        if not gripper.present(scenario):
            return None
        geometry = gripper.geometry(scenario)
        model = self.gripper_model(scenario)
        length = geometry.finger_length
        return GripperConfig(
            node=gripper.node(scenario),
            x_start=self.gripper_cylinder(scenario)["x_start"],
            x_open=model.piston_for_curvature(geometry.theta_open / length),
            x_closed=model.piston_for_curvature(geometry.theta_closed / length),
            geometry=geometry,
        )

    # ------------------------------------------------------------------ task space

    def curvature_limits(self, scenario: Scenario) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each segment's reachable curvature range at full stroke (from its static equilibrium
        with the sealed gas circuits, PHYSICS.md section 2) and the curvature rate the drive can
        follow: its no-load speed u_max / Ke * lead / (2 pi), derated by DRIVE_SPEED_SHARE for the
        load, times the segment's curvature per piston travel (1/m per m)."""
        lower, upper, rates = [], [], []
        for model, cylinder in zip(
            self.segment_models(scenario), self.parameters(scenario, "cylinder"), strict=True
        ):
            lo, hi = model.reachable_curvature()
            lower.append(lo)
            upper.append(hi)
            speed = cylinder["u_max"] / cylinder["Ke"] * cylinder["lead"] / (2.0 * math.pi)
            rates.append(DRIVE_SPEED_SHARE * speed * abs(model.static_gain()))
        return np.array(lower), np.array(upper), np.array(rates)

    def task_plan(self, scenario: Scenario) -> TaskPlan | None:
        """The task-space plan the controller pursues and the plant scores (None for a curvature
        profile): explicit targets or paths, or drawn from the scenario's seed."""
        task = scenario.task
        if task.kind not in TASK_KINDS:
            return None
        lower, upper, rates = self.curvature_limits(scenario)
        lengths = [p["length"] for p in self.parameters(scenario, "segment")]
        base = scenario.robot.base
        rng = np.random.default_rng([scenario.seed, TASK_STREAM])
        targets: tuple[tuple[float, float], ...]
        ends: tuple[tuple[float, float], ...] = ()
        walls: tuple[tuple[tuple[float, float], ...], ...] = ()
        width = 0.0
        object_radius = 0.0
        if task.kind == "grasp":  # the controller is told where to place it, not where it is
            targets = (self.grasp_layout(scenario)[1],)
            object_radius = float(self.grasp_object(scenario)["radius"])
        elif task.kind == "pipe":
            assert task.goal is not None  # checked
            targets = (task.goal,)
            walls = tuple(
                tuple((float(x), float(y)) for x, y in wall)
                for wall in scenario.robot.environment.get("walls", [])
            )
            width = max(
                environment.parameters(
                    scenario,
                    self.parameters(scenario, "segment"),
                    ACTUATOR_WIDTH[scenario.robot.actuator],
                )[f"width_{n}"]
                for n in range(1, scenario.robot.segments + 1)
            )
        elif task.kind == "point_to_point":
            targets = task.targets or tuple(
                draw_targets(rng, lengths, base, lower, upper, task.count, task.margin)
            )
        elif task.paths:
            targets = tuple((p[0], p[1]) for p in task.paths)
            ends = tuple((p[2], p[3]) for p in task.paths)
        else:
            paths = draw_paths(
                rng, lengths, base, lower, upper, task.count, task.path_length, task.margin
            )
            targets = tuple(a for a, _ in paths)
            ends = tuple(b for _, b in paths)
        mid, half = 0.5 * (lower + upper), 0.5 * (upper - lower) * IK_RANGE_SHARE
        return TaskPlan(
            kind=task.kind,
            targets=tuple(targets),
            ends=ends,
            kappa_min=tuple(float(v) for v in mid - half),
            kappa_max=tuple(float(v) for v in mid + half),
            kappa_rate=tuple(float(v) for v in rates),
            walls=walls,
            width=width,
            object_radius=object_radius,
            **{name: getattr(task, name) for name in PLAN_KEYS},
        )

    # ------------------------------------------------------------------ scoring

    def task_metrics(self, scenario: Scenario, signals: Mapping[str, Any]) -> dict[str, Any]:
        from hil.summary import curvature_metrics

        if scenario.task.kind in TASK_KINDS:
            from robots.planar_arm.plant.tasks import task_space_metrics

            return task_space_metrics(self, scenario, signals)
        return curvature_metrics(scenario, signals)


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
        **{k: values[k] for k in SegmentModel.__dataclass_fields__ if k != "x_seal"},
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


ROBOT = PlanarArm()
