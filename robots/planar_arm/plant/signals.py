"""What a planar arm's run records and plots: each segment's signals, the gripper's, the
environment's and the task's; and the frames the bus carries, at the rates expected of them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from hil.devices import HEARTBEAT_PERIOD
from hil.rig import PlotSpec, SignalSpec
from rigbus.protocol import Protocol
from robots.planar_arm.controller.tasks import TASK_KINDS
from robots.planar_arm.plant import body, environment, gripper
from robots.planar_arm.plant.configuration import markers

if TYPE_CHECKING:
    from hil.scenario import Scenario

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
    "x": "cylinder{n}.x",
    "x_ref": "drive{n}.x_ref",
    "v": "cylinder{n}.v",
    "i_motor": "cylinder{n}.i_motor",
    "fault": "drive{n}.fault",
}


def signals(scenario: Scenario) -> list[SignalSpec]:
    specs = []
    for n in range(1, scenario.robot.segments + 1):
        arm = body.arm_ports(scenario, n)  # kappa, theta, p_a, p_b: the segment's or the body's
        for name, unit, description in PER_SEGMENT:
            column = f"{name}_{n}"
            text = f"segment {n}: {description}"
            if name in ("kappa_ref", "kappa_est"):
                specs.append(SignalSpec(column, unit, text, frame=("ControllerState", n, name)))
            elif name in arm:
                specs.append(SignalSpec(column, unit, text, source=arm[name]))
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


def plots(scenario: Scenario) -> list[PlotSpec]:
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


def frame_rates(scenario: Scenario, protocol: Protocol) -> dict[str, float]:
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
    for m in range(markers(scenario)):
        rates[f"CameraMarker{m}"] = scenario.camera.rate
    return rates
