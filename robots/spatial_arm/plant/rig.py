"""The spatial arm: one ArmBody FMU (every segment's two bending coordinates, the inertia between
segments, gravity), a DriveCylinder FMU and a drive-firmware node per antagonistic channel pair,
and the camera seeing a marker at the base, at every endplate and on the task's object, in 3-D.

Drive numbering: segment i's x pair is drive 2i - 1, its y pair drive 2i (the x pair bends the
segment towards its base frame's +x as its piston advances). Positions are in the arm's base
frame: z along the straight arm, x towards the first segment's x pair; the camera is calibrated
to it. The base pose says where gravity points in that frame: `horizontal` (the arm held out
level, +x up, where gravity loads it most) or `down` (hanging).

Parameters: `[robot.body]` takes ArmBody's (per segment as `L_1`, `k_2`, ...: fmus/ArmBody),
`[robot.cylinder]` the drive cylinders' (every pair's cylinder alike; bore, stroke and sealing
position are the body's, where its gas circuits are declared).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from hil.cosim import Connection, FmuParticipant, Participant
from hil.devices import CameraNode, DriveNode
from hil.rig import Rig, fmu_ref, scenario_camera
from hil.schema import Needs, OneOf, Range, Table, setting
from rigbus.protocol import Protocol
from robots.spatial_arm.plant import signals as signal_specs

if TYPE_CHECKING:
    from hil.scenario import Scenario
    from robots.spatial_arm.controller.config import SpatialConfig

BODY_FMU = "ArmBody"
CYLINDER_FMU = "DriveCylinder"
TASKS = ("configuration", "point", "object", "shape", "confined")
GRAVITY = 9.81  # [m/s^2]
# where gravity points in the base frame, per base pose (the straight arm along base z)
BASE_POSES = {"horizontal": (-1.0, 0.0, 0.0), "down": (0.0, 0.0, 1.0)}
# body parameters that come from elsewhere in the scenario
BODY_REFUSED = ("n_segments", "planar", "g_x", "g_y", "g_z")
BODY_REFUSED_WHY = "robot.segments, robot.pose and robot.gravity set them"
CYLINDER_REFUSED = ("bore", "stroke", "x_start")
CYLINDER_REFUSED_WHY = "the body's bore, stroke and x_seal (one gas circuit per pair)"
# [estimate] the thesis's spatial arm uses high-capacity drive cylinders: the default
# DriveCylinder's 12 V motor stalls near 60 kPa on the body's 1.25 in bore, below the ~75 kPa
# the base pair needs at full stroke; a 24 V supply doubles the force the screw can hold
# [derived] its larger bore makes the mechanics stiffer: the default 0.5 ms substep is beyond
# its stability limit (0.45 ms), a quarter millisecond is within it
CYLINDER_DEFAULTS = {"u_max": 24.0, "substep": 2.5e-4}


@dataclass(frozen=True)
class SpatialArmSpec:
    """The `[robot]` section of the spatial arm."""

    kind: str = setting("spatial_arm", doc="the robot kind")
    segments: int = setting(
        4, "", "segments, each with two channel pairs (two drives)", Range(1, 8, why="ArmBody's")
    )
    pose: str = setting(
        "horizontal",
        doc="the base pose: where gravity points in the arm's base frame",
        choices={"horizontal": "the arm held out level, base +x up", "down": "hanging"},
    )
    gravity: float = setting(GRAVITY, "m/s^2", "gravity's magnitude (0: none)", Range(0, 100))
    body: dict[str, Any] = setting(factory=dict, doc="ArmBody parameters ([robot.body])")
    cylinder: dict[str, Any] = setting(
        factory=dict, doc="DriveCylinder parameters of every pair's cylinder ([robot.cylinder])"
    )
    estimator: str = setting(
        "kf",
        doc="the controller's bend estimator",
        choices={
            "kf": "Kalman filter on the bends, predicted towards the gravity-loaded equilibrium",
            "ik": "each picture's single-segment inverse kinematics, unfiltered",
        },
    )
    goals: tuple[tuple[float, float, float], ...] = setting(
        (), "m", "point: goals [x, y, z] (absent: task.count drawn inside the envelope)"
    )
    bends: tuple[tuple[float, ...], ...] = setting(
        (),
        "s, rad",
        "configuration: steps [time, theta_x_1, theta_y_1, ...] (absent: drawn from the seed)",
    )
    object: tuple[float, float, float] | None = setting(
        None, "m", "object: the object's centre [x, y, z] (absent: drawn inside the envelope)"
    )
    offset: tuple[float, float, float] = setting(
        (0.0, 0.0, 0.0), "m", "object: where the tip goes relative to the object's marker"
    )
    curve: tuple[tuple[float, float, float], ...] = setting(
        (), "m", "shape: the curve's points [x, y, z] from the base (absent: drawn)"
    )
    pipe: tuple[tuple[float, float, float], ...] = setting(
        (), "m", "confined: the pipe's axis [x, y, z] points, the first its entrance"
    )
    pipe_radius: float = setting(
        0.03, "m", "confined: the pipe's inner radius", Range(0, lo_open=True)
    )
    goal_depth: float = setting(
        0.06,
        "m",
        "confined: the tip's goal past the entrance, along the axis",
        Range(0, lo_open=True),
    )
    width: float = setting(
        0.03, "m", "the arm's width (diameter) [estimate]", Range(0, lo_open=True)
    )
    insertion_step: float = setting(
        0.02, "m", "confined: the tip's advance between planned stations", Range(0, lo_open=True)
    )
    speed: float = setting(
        0.5, "rad/s", "the largest bend rate of a trapezoidal move", Range(0, lo_open=True)
    )
    acceleration: float = setting(
        1.0, "rad/s^2", "the bend acceleration of a trapezoidal move", Range(0, lo_open=True)
    )
    envelope_samples: int = setting(
        1500, "", "static equilibria sampled for the reachable envelope", Range(50, 100000)
    )

    RULES: ClassVar[tuple[Any, ...]] = (Needs("task.kind", OneOf(TASKS)),)
    TABLES: ClassVar[tuple[Table, ...]] = (
        Table(
            "robot.body",
            (),
            fmu=BODY_FMU,
            checked=False,
            doc="the arm body's ArmBody parameters (per segment: L_1, k_2, ...)",
            refused=BODY_REFUSED,
            refused_why=BODY_REFUSED_WHY,
        ),
        Table(
            "robot.cylinder",
            (),
            fmu=CYLINDER_FMU,
            checked=False,
            doc="every pair's DriveCylinder parameters",
            starts=CYLINDER_DEFAULTS,
            refused=CYLINDER_REFUSED,
            refused_why=CYLINDER_REFUSED_WHY,
        ),
    )


def drives(scenario: Scenario) -> int:
    """Drive nodes: two per segment."""
    return 2 * int(scenario.robot.segments)


def drive_of(segment: int, axis: str) -> int:
    """The drive node of segment `segment`'s (1-based) `axis` ("x" or "y") pair."""
    return 2 * segment - (1 if axis == "x" else 0)


class SpatialArm:
    name = "spatial_arm"
    spec_class = SpatialArmSpec
    estimation_report = False  # `hil estimate` scores the planar arm's curvature estimators

    # ------------------------------------------------------------------ parameters

    def _table(self, scenario: Scenario, table: str) -> dict[str, float]:
        from hil.scenario import check_parameter, fail, fmu_interface

        fmu = BODY_FMU if table == "body" else CYLINDER_FMU
        refused, why = (
            (BODY_REFUSED, BODY_REFUSED_WHY)
            if table == "body"
            else (CYLINDER_REFUSED, CYLINDER_REFUSED_WHY)
        )
        interface = fmu_interface(scenario.source, f"robot.{table}", fmu)
        values: dict[str, float] = {}
        for name, value in getattr(scenario.robot, table).items():
            key = f"robot.{table}.{name}"
            if name in refused:
                raise fail(scenario.source, key, why)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise fail(scenario.source, key, f"must be a number, got {value!r}")
            check_parameter(scenario.source, key, interface, name, float(value))
            values[name] = float(value)
        return values

    def given_body(self, scenario: Scenario) -> dict[str, float]:
        """The body's parameters the rig sets: the scenario's, the segments, the gravity."""
        r: SpatialArmSpec = scenario.robot
        g = [r.gravity * c for c in BASE_POSES[r.pose]]
        return {
            **self._table(scenario, "body"),
            "n_segments": float(r.segments),
            "planar": 0.0,
            "g_x": g[0],
            "g_y": g[1],
            "g_z": g[2],
        }

    def body_parameters(self, scenario: Scenario) -> dict[str, float]:
        """Every parameter of the body: the rig's, else the FMU's default."""
        return {**_defaults(scenario, "robot.body", BODY_FMU), **self.given_body(scenario)}

    def given_cylinder(self, scenario: Scenario) -> dict[str, float]:
        body = self.body_parameters(scenario)
        return {
            **CYLINDER_DEFAULTS,
            **self._table(scenario, "cylinder"),
            "bore": body["bore"],
            "stroke": body["stroke"],
            "x_start": body["x_seal"],
        }

    def cylinder_parameters(self, scenario: Scenario) -> dict[str, float]:
        return {
            **_defaults(scenario, "robot.cylinder", CYLINDER_FMU),
            **self.given_cylinder(scenario),
        }

    # ------------------------------------------------------------------ checks

    def check(self, scenario: Scenario) -> None:
        """The checks that are code: the FMU tables, the goals' and curve's shapes, the start."""
        from robots.spatial_arm.plant.checks import check

        check(self, scenario)

    def ports(self, scenario: Scenario) -> dict[str, tuple[set[str], set[str]]]:
        from hil.scenario import fmu_interface

        ports: dict[str, tuple[set[str], set[str]]] = {
            "camera": (set(), set(self.camera_inputs(scenario)))
        }
        for name, table, fmu in (("body", "robot.body", BODY_FMU),):
            interface = fmu_interface(scenario.source, table, fmu)
            ports[name] = (
                {n for n, v in interface.items() if v.causality == "output"},
                {n for n, v in interface.items() if v.causality == "input"},
            )
        interface = fmu_interface(scenario.source, "robot.cylinder", CYLINDER_FMU)
        for n in range(1, drives(scenario) + 1):
            ports[f"cylinder{n}"] = (
                {k for k, v in interface.items() if v.causality == "output"},
                {k for k, v in interface.items() if v.causality == "input"},
            )
            ports[f"drive{n}"] = ({"x_ref", "enable", "fault"}, {"x", "p_a", "p_b", "servo_fault"})
        return ports

    def reach(self, scenario: Scenario) -> float:
        """Farthest a marker can be from the base [m]: the arm's length with its end pieces."""
        body = self.body_parameters(scenario)
        return sum(
            body[f"L_{i}"] + 2.0 * body[f"L_p_{i}"] for i in range(1, scenario.robot.segments + 1)
        )

    def camera_inputs(self, scenario: Scenario) -> list[str]:
        """What the camera sees: every endplate's position (the base marker is fixed)."""
        return [f"tip_{c}_{i}" for i in range(1, scenario.robot.segments + 1) for c in "xyz"]

    def markers(self, scenario: Scenario) -> int:
        """Markers: the base, every endplate, the task's object."""
        return scenario.robot.segments + 1 + (1 if scenario.task.kind == "object" else 0)

    # ------------------------------------------------------------------ the task

    def model(self, scenario: Scenario) -> Any:
        """The controller's model of this arm (robots.spatial_arm.controller.model)."""
        from robots.spatial_arm.controller.model import ArmModel

        return ArmModel.from_fmu_parameters(self.body_parameters(scenario))

    def start_bends(self, scenario: Scenario) -> np.ndarray:
        """The arm's start: at rest on its passive equilibrium under gravity (every piston at
        its sealing position), so that a run starts settled, drooped as the real arm hangs."""
        from robots.spatial_arm.plant.task import start_bends

        return start_bends(self, scenario)

    def task_layout(self, scenario: Scenario) -> Any:
        """The task's goals, object, curve or bend steps: given, else drawn from the seed."""
        from robots.spatial_arm.plant.task import layout

        return layout(self, scenario)

    def envelope(self, scenario: Scenario, samples: int | None = None) -> Any:
        """The statically reachable envelope (`hil envelope`): robot.envelope_samples rests."""
        from robots.spatial_arm.plant import envelope_view

        return envelope_view.envelope(self, scenario, samples)

    def envelope_report(self, scenario: Scenario, envelope: Any) -> str:
        from robots.spatial_arm.plant import envelope_view

        return envelope_view.report(self, scenario, envelope)

    def envelope_files(self, envelope: Any) -> dict[str, bytes]:
        from robots.spatial_arm.plant import envelope_view

        return envelope_view.files(envelope)

    def draw_envelope(self, scenario: Scenario, envelope: Any, path: Path) -> None:
        from robots.spatial_arm.plant import envelope_view

        envelope_view.draw(self, scenario, envelope, path)

    # ------------------------------------------------------------------ the rig

    def build(self, scenario: Scenario) -> Rig:
        """Drive n's firmware sets cylinder n's setpoint and watches its position and its pair's
        pressures; cylinder n moves its pair's piston in the body and feels its pressures; the
        camera sees every endplate and the object. Scenario connections replace defaults that
        drive the same input, and add the others."""
        from hil.fmu.slave import FmuSlave

        r: SpatialArmSpec = scenario.robot
        protocol = Protocol()
        n_drives = drives(scenario)
        cylinder = self.cylinder_parameters(scenario)
        x_start = cylinder["x_start"]
        timeout_ticks = round(scenario.safety.command_timeout / scenario.timing.step)
        drive_nodes = [
            DriveNode(
                n,
                x_start,
                x_start,
                scenario.safety.max_pressure,
                timeout_ticks,
                position_range=protocol.signal_range(f"DriveStatus{n}", "piston_position"),
                pressure_range=protocol.signal_range(f"DriveStatus{n}", "p_a"),
                decimation=scenario.control_ticks,
            )
            for n in range(1, n_drives + 1)
        ]
        layout = self.task_layout(scenario)
        camera = CameraNode(
            self.camera_inputs(scenario),
            _marker_model(r.segments, layout.object),
            scenario.latency_ticks,
            scenario_camera(scenario),
            dims=3,
        )
        start = self.start_bends(scenario)
        body_values = dict(self.given_body(scenario))
        for i in range(r.segments):
            body_values[f"theta_x_start_{i + 1}"] = float(start[2 * i])
            body_values[f"theta_y_start_{i + 1}"] = float(start[2 * i + 1])
        fmus: list[FmuParticipant] = []
        parameters: dict[str, Mapping[str, float]] = {}
        try:
            body = FmuSlave(
                fmu_ref(scenario.source, BODY_FMU), "body", body_values, exit_initialization=False
            )
            fmus.append(FmuParticipant(body, 1))
            parameters["body"] = {**self.body_parameters(scenario), **body_values}
            for n in range(1, n_drives + 1):
                slave = FmuSlave(
                    fmu_ref(scenario.source, CYLINDER_FMU),
                    f"cylinder{n}",
                    self.given_cylinder(scenario),
                    exit_initialization=False,
                )
                fmus.append(FmuParticipant(slave, 1))
                parameters[f"cylinder{n}"] = cylinder
        except BaseException:
            for participant in fmus:
                participant.close()
            raise
        connections: dict[str, Connection] = {}
        for source, target in wiring(r.segments):
            connections[target] = Connection(source, target)
        for c in scenario.connections:
            connections[c.target] = Connection(c.source, c.target, c.gain, c.offset)
        participants: list[Participant] = [*fmus, *drive_nodes, camera]

        def draw(signals: Mapping[str, Any], path: Path) -> None:
            from robots.spatial_arm.plant.figures import draw_arm

            draw_arm(self, scenario, signals, path)

        def animate(signals: Mapping[str, Any], path: Path, fmt: str) -> None:
            from robots.spatial_arm.plant.figures import animate_arm

            animate_arm(self, scenario, signals, path, fmt)

        figures: list[tuple[str, Any]] = [("arm", draw)]
        if scenario.task.kind == "confined":

            def confining(signals: Mapping[str, Any], path: Path) -> None:
                from robots.spatial_arm.plant.figures import draw_confining
                from robots.spatial_arm.plant.metrics import confining_rows

                draw_confining(confining_rows(self, scenario), scenario.name, path)

            figures.append(("confining", confining))
        return Rig(
            participants,
            list(connections.values()),
            [*drive_nodes, camera],
            self.signals(scenario),
            self.plots(scenario),
            parameters,
            figures,
            animation=("arm", animate),
        )

    def signals(self, scenario: Scenario) -> list[Any]:
        return signal_specs.signals(scenario.robot.segments)

    def plots(self, scenario: Scenario) -> list[Any]:
        return signal_specs.plots(scenario.robot.segments)

    def frame_rates(self, scenario: Scenario, protocol: Protocol) -> dict[str, float]:
        return signal_specs.frame_rates(
            drives(scenario),
            self.markers(scenario),
            scenario.timing.control_period,
            scenario.camera.rate,
        )

    # ------------------------------------------------------------------ the controller side

    def controller_config(self, scenario: Scenario) -> SpatialConfig:
        from robots.spatial_arm.plant.task import controller_config

        return controller_config(self, scenario)

    def task_metrics(self, scenario: Scenario, signals: Mapping[str, Any]) -> dict[str, Any]:
        from robots.spatial_arm.plant.metrics import task_metrics

        return task_metrics(self, scenario, signals)


def wiring(segments: int) -> list[tuple[str, str]]:
    """(source, target) of every default connection: each pair's drive, cylinder and body
    inputs and outputs, and the endplates to the camera."""
    links: list[tuple[str, str]] = []
    for i in range(1, segments + 1):
        for axis in "xy":
            n = drive_of(i, axis)
            links += [
                (f"cylinder{n}.x", f"body.x_piston_{axis}_{i}"),
                (f"body.p_a_{axis}_{i}", f"cylinder{n}.p_a"),
                (f"body.p_b_{axis}_{i}", f"cylinder{n}.p_b"),
                (f"drive{n}.x_ref", f"cylinder{n}.x_ref"),
                (f"drive{n}.enable", f"cylinder{n}.enable"),
                (f"cylinder{n}.x", f"drive{n}.x"),
                (f"body.p_a_{axis}_{i}", f"drive{n}.p_a"),
                (f"body.p_b_{axis}_{i}", f"drive{n}.p_b"),
                (f"cylinder{n}.fault", f"drive{n}.servo_fault"),
            ]
        for c in "xyz":
            links.append((f"body.tip_{c}_{i}", f"camera.tip_{c}_{i}"))
    return links


def _marker_model(segments: int, obj: Sequence[float] | None) -> Any:
    """The camera's view: the base marker at the origin, every endplate, the object's centre."""
    fixed_tail = [list(map(float, obj))] if obj is not None else []

    def model(values: Sequence[float]) -> np.ndarray:
        rows = [[0.0, 0.0, 0.0]]
        rows += [list(values[3 * i : 3 * i + 3]) for i in range(segments)]
        return np.array(rows + fixed_tail, dtype=float)

    return model


def _defaults(scenario: Scenario, key: str, fmu: str) -> dict[str, float]:
    """An FMU's parameters' start values."""
    from hil.scenario import fmu_interface

    return {
        name: float(port.start)
        for name, port in fmu_interface(scenario.source, key, fmu).items()
        if port.causality == "parameter" and port.start is not None
    }
