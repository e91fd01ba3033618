"""The planar arm's controller side, as the controller node runs it (`rigbus.robots`): its
configuration (`config_class`), its estimator (`make_estimator`), its controller for the task
(`make_controller`: curvature tracking, task space, grasp-and-place), the status frames every
cycle must bring (`expected`) and what the estimator sees of them (`readings`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from controllers.estimation import DriveReading
from rigbus.protocol import Protocol
from robots.planar_arm.controller.config import ControllerConfig
from robots.planar_arm.controller.curvature_control import CurvatureControl
from robots.planar_arm.controller.grasp_control import GraspControl
from robots.planar_arm.controller.task_space import TaskSpaceControl


def expected(config: ControllerConfig) -> set[tuple[str, int | None]]:
    """The status frames every cycle must bring: each drive's (the gripper's too)."""
    drives: set[tuple[str, int | None]] = {
        ("DriveStatus", n) for n in range(1, config.segments + 1)
    }
    if config.gripper is not None:
        drives.add(("DriveStatus", config.gripper.node))
    return drives


def readings(status: Mapping[tuple[str, int | None], Any]) -> dict[int, DriveReading]:
    """Each drive's reading by node, from the cycle's DriveStatus frames."""
    return {
        key[1]: DriveReading(s.piston_position, s.p_a, s.p_b, s.fault)
        for key, s in status.items()
        if key[0] == "DriveStatus" and key[1] is not None
    }


def make_estimator(config: ControllerConfig) -> Any:
    """The estimator the configuration names (controllers.estimators), with the objects'
    tracker (controllers.object_tracking) when the task has objects."""
    from controllers import estimators, object_tracking

    arm = estimators.make_estimator(
        config.estimator,
        config.bends,
        config.base,
        config.camera,
        config.control_period,
        config.latency_compensation,
        config.torque_std,
        config.masses,
    )
    if config.objects == 0:
        return arm
    tracker = object_tracking.ObjectTracker(config.objects, config.camera)
    return object_tracking.WithObjects(arm, config.segments + 1, tracker)


def make_controller(config: ControllerConfig, protocol: Protocol) -> Any:
    """Curvature tracking of the task's profile, or task-space control when the configuration
    carries a task plan (point-to-point, path)."""
    if config.plan is not None and config.plan.kind == "grasp":
        return GraspControl(config, protocol)
    if config.plan is not None:
        return TaskSpaceControl(config, protocol)
    return CurvatureControl(config, protocol)


config_class = ControllerConfig
