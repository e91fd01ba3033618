"""The planar arm: per segment a DriveCylinder FMU, a FeaSegment FMU
and a drive-firmware node; one camera seeing a marker at the base and at every segment end.

PlanarArm is the robot kind the rest of softhil calls (rigbus.robots): it builds the rig and
names each participant's ports here, and takes the rest from its modules: the `[robot]` section
and the per-actuator parameters from parameters.py, the models, the task plan and the
controller's configuration from configuration.py, the signals, plots and frame rates from
signals.py, the scenario checks from checks.py.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from controllers import kinematics
from controllers.curvature import SegmentModel
from hil.cosim import Connection, FmuParticipant, Participant
from hil.devices import CameraNode, DriveNode
from hil.rig import PlotSpec, Rig, SignalSpec, fmu_ref, scenario_camera
from rigbus.protocol import Protocol
from robots.planar_arm.controller.config import ControllerConfig, GripperConfig
from robots.planar_arm.controller.tasks import TASK_KINDS, TaskPlan
from robots.planar_arm.plant import body, checks, configuration, environment, gripper
from robots.planar_arm.plant import parameters as arm_parameters
from robots.planar_arm.plant import signals as arm_signals
from robots.planar_arm.plant.parameters import (
    NAME,
    PlanarArmSpec,
    _interface,
)

if TYPE_CHECKING:
    from hil.scenario import Scenario


class PlanarArm:
    """The planar arm robot kind: it builds the rig, names each participant's ports, runs the
    scenario checks and scores a run; its other methods are the functions of the same name in
    parameters.py, configuration.py and signals.py."""

    name = NAME
    spec_class = PlanarArmSpec

    # ------------------------------------------------------------------ parameters

    def given(self, scenario: Scenario, table: str) -> list[dict[str, float]]:
        return arm_parameters.given(scenario, table)

    def _given(self, scenario: Scenario, table: str) -> list[dict[str, tuple[float, str]]]:
        return arm_parameters._given(scenario, table)

    def parameters(self, scenario: Scenario, table: str) -> list[dict[str, float]]:
        return arm_parameters.parameters(scenario, table)

    # ------------------------------------------------------------------ checks

    def check(self, scenario: Scenario) -> None:
        """The arm's scenario checks that are code (robots.planar_arm.plant.checks)."""
        checks.check(self, scenario)

    def environment_parameters(self, s: Scenario) -> dict[str, float]:
        return configuration.environment_parameters(s)

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
        if body.present(scenario):
            interface = fmu_interface(scenario.source, "robot.model", body.FMU)
            ports[body.NAME] = (*_split(interface),)
            del interfaces["segment"]
        for i in range(1, r.segments + 1):
            for kind, interface in interfaces.items():
                ports[f"{kind}{i}"] = (*_split(interface),)
            ports[f"drive{i}"] = ({"x_ref", "enable", "fault"}, {"x", "p_a", "p_b", "servo_fault"})
        if gripper.present(scenario):
            g = gripper.node(scenario)
            for kind, fmu in (("gripper", gripper.SEGMENT_FMU), (f"cylinder{g}", "DriveCylinder")):
                interface = fmu_interface(scenario.source, "robot.gripper", fmu)
                ports[kind] = (*_split(interface),)
            ports[f"drive{g}"] = ({"x_ref", "enable", "fault"}, {"x", "p_a", "p_b", "servo_fault"})
        if environment.present(scenario):
            interface = fmu_interface(scenario.source, "robot.environment", environment.FMU)
            ports["environment"] = (*_split(interface),)
        return ports

    def start_pistons(self, scenario: Scenario) -> list[float]:
        return configuration.start_pistons(scenario)

    def camera_inputs(self, scenario: Scenario) -> list[str]:
        return configuration.camera_inputs(scenario)

    def gripper_cylinder(self, scenario: Scenario) -> dict[str, float]:
        return configuration.gripper_cylinder(scenario)

    def gripper_model(self, scenario: Scenario) -> SegmentModel:
        return configuration.gripper_model(scenario)

    def grasp_layout(self, scenario: Scenario) -> tuple[tuple[float, float], tuple[float, float]]:
        return configuration.grasp_layout(scenario)

    def grasp_object(self, scenario: Scenario) -> dict[str, float]:
        return configuration.grasp_object(scenario)

    def reach(self, scenario: Scenario) -> float:
        return configuration.reach(scenario)

    # ------------------------------------------------------------------ the rig

    def build(self, scenario: Scenario) -> Rig:
        """For each n: drive n's firmware sets cylinder n's setpoint and watches its position
        and segment n's pressures; cylinder n moves segment n's piston and feels its pressures;
        the camera sees every segment's curvature. Scenario connections replace defaults that
        drive the same input, and add the others."""
        from hil.fmu.slave import FmuSlave

        r: PlanarArmSpec = scenario.robot
        protocol = Protocol()
        segments = self.parameters(scenario, "segment")
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
            self._arm(scenario, pistons, fmus, connections, parameters)
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
                ports = [body.arm_ports(scenario, n) for n in range(1, r.segments + 1)]
                for source, target in environment.connections(ports):
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

    def _arm(
        self,
        scenario: Scenario,
        pistons: Sequence[float],
        fmus: list[FmuParticipant],
        connections: dict[str, Connection],
        parameters: dict[str, Mapping[str, float]],
    ) -> None:
        """The arm's FMUs (appended to `fmus` as they open), their connections and parameters:
        each segment's drive cylinder, and one ArmBody for every segment (robot.model = "body")
        or a FeaSegment per segment."""
        from hil.fmu.slave import FmuSlave

        r: PlanarArmSpec = scenario.robot
        cylinders_given = self.given(scenario, "cylinder")
        segments_given = self.given(scenario, "segment")
        segments = self.parameters(scenario, "segment")
        cylinders = self.parameters(scenario, "cylinder")
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
            parameters[f"cylinder{n}"] = cylinders[n - 1]
        if body.present(scenario):
            body_values = body.values(segments, cylinders)
            arm = FmuSlave(body.FMU, body.NAME, body_values, exit_initialization=False)
            fmus.append(FmuParticipant(arm, r.segment_decimation))
            parameters[body.NAME] = body_values
        else:
            names = {
                n for n, p in _interface(scenario, "segment").items() if p.causality == "parameter"
            }
            for n in range(1, r.segments + 1):
                # the segment's gas circuit includes the cylinder: same bore and stroke, sealed
                # where the piston starts
                geometry = {
                    "bore": cylinders[n - 1]["bore"],
                    "stroke": cylinders[n - 1]["stroke"],
                    "x_seal": cylinders[n - 1]["x_start"],
                }
                segment_values = {
                    **{k: v for k, v in geometry.items() if k in names},
                    **segments_given[n - 1],
                }
                segment = FmuSlave(
                    fmu_ref(scenario.source, r.segment_fmu),
                    f"segment{n}",
                    segment_values,
                    exit_initialization=False,
                )
                fmus.append(FmuParticipant(segment, r.segment_decimation))
                parameters[f"segment{n}"] = {**segments[n - 1], **segment_values}
        for n in range(1, r.segments + 1):
            ports = body.arm_ports(scenario, n)
            for source, target in (
                *gripper.drive_connections(n, ports),
                (ports["kappa"], f"camera.kappa_{n}"),
            ):
                connections[target] = Connection(source, target)

    def signals(self, scenario: Scenario) -> list[SignalSpec]:
        return arm_signals.signals(scenario)

    def plots(self, scenario: Scenario) -> list[PlotSpec]:
        return arm_signals.plots(scenario)

    def frame_rates(self, scenario: Scenario, protocol: Protocol) -> dict[str, float]:
        return arm_signals.frame_rates(scenario, protocol)

    # ------------------------------------------------------------------ the controller side

    def segment_models(self, scenario: Scenario) -> list[SegmentModel]:
        return configuration.segment_models(scenario)

    def controller_config(self, scenario: Scenario) -> ControllerConfig:
        return configuration.controller_config(scenario)

    def markers(self, scenario: Scenario) -> int:
        return configuration.markers(scenario)

    def gripper_config(self, scenario: Scenario) -> GripperConfig | None:
        return configuration.gripper_config(scenario)

    # ------------------------------------------------------------------ task space

    def curvature_limits(self, scenario: Scenario) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return configuration.curvature_limits(scenario)

    def task_plan(self, scenario: Scenario) -> TaskPlan | None:
        return configuration.task_plan(scenario)

    # ------------------------------------------------------------------ scoring

    def task_metrics(self, scenario: Scenario, signals: Mapping[str, Any]) -> dict[str, Any]:
        from hil.summary import curvature_metrics

        if scenario.task.kind in TASK_KINDS:
            from robots.planar_arm.plant.tasks import task_space_metrics

            return task_space_metrics(self, scenario, signals)
        return curvature_metrics(scenario, signals)


def _split(interface: Mapping[str, Any]) -> tuple[set[str], set[str]]:
    """An FMU's (outputs, inputs) by name."""
    return (
        {n for n, v in interface.items() if v.causality == "output"},
        {n for n, v in interface.items() if v.causality == "input"},
    )


ROBOT = PlanarArm()
