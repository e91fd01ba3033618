"""The planar arm's controller side: its estimator and its curvature controllers.

`make_estimator` returns the estimator the configuration names; `CurvatureControl` runs one
curvature PI per segment (PHYSICS.md section 4) and answers each cycle with a DriveCommand and a
ControllerState frame per segment (the reference it tracks and the estimate it used).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from controllers.curvature import CurvaturePI
from controllers.estimation import DriveReading, Estimate
from rigbus.protocol import ControllerState, DriveCommand, Protocol

if TYPE_CHECKING:
    from controllers.kinematics import Floats
    from controllers.node import ControllerConfig


def __getattr__(name: str) -> Any:
    """`config_class`: the arm's ControllerConfig (controllers.node imports this module)."""
    if name == "config_class":
        from controllers.node import ControllerConfig

        return ControllerConfig
    raise AttributeError(name)


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
    """The estimator the configuration names (controllers.estimators)."""
    from controllers import estimators

    arm = estimators.make_estimator(
        config.estimator,
        config.bends,
        config.base,
        config.camera,
        config.control_period,
        config.latency_compensation,
        config.torque_std,
    )
    if config.objects == 0:
        return arm
    tracker = estimators.ObjectTracker(config.objects, config.camera)
    return estimators.WithObjects(arm, config.segments + 1, tracker)


class CurvatureControl:
    """One curvature PI per segment; references from the task's profile."""

    def __init__(self, config: ControllerConfig, protocol: Protocol) -> None:
        self.config = config
        self.pis = [
            CurvaturePI(
                config.gains[i],
                config.control_period,
                config.x_mid[i],
                config.x_min[i],
                config.x_max[i],
                config.feedforward[i] if config.feedforward else 0.0,
            )
            for i in range(config.segments)
        ]
        # the state frame is for recording: an estimate beyond its range is shown saturated
        self.shown_range = protocol.signal_range("ControllerState1", "kappa_est")

    def compute(
        self, cycle: int, t: float, estimate: Estimate, drives: Mapping[int, DriveReading]
    ) -> list[Any]:
        references = [self.config.profile.for_segment(i, t) for i in range(len(self.pis))]
        return self.command(cycle, references, estimate, drives)

    def command(
        self,
        cycle: int,
        references: Floats,
        estimate: Estimate,
        drives: Mapping[int, DriveReading],
    ) -> list[Any]:
        """Each segment's PI towards its curvature reference: a DriveCommand and a
        ControllerState frame per segment."""
        frames: list[Any] = []
        lo, hi = self.shown_range
        for i, pi in enumerate(self.pis):
            node = i + 1
            kappa_ref = float(references[i])
            reading = drives.get(node)
            piston = reading.piston_position if reading is not None else None
            kappa_est = float(estimate.kappa[i])
            setpoint = pi.update(kappa_ref, kappa_est, piston)
            frames.append(DriveCommand(node, setpoint, True, cycle))
            frames.append(ControllerState(node, kappa_ref, min(max(kappa_est, lo), hi), cycle))
        return frames


def make_controller(config: ControllerConfig, protocol: Protocol) -> Any:
    """Curvature tracking of the task's profile, or task-space control when the configuration
    carries a task plan (point-to-point, path)."""
    if config.plan is not None and config.plan.kind == "grasp":
        from controllers.grasp_control import GraspControl

        return GraspControl(config, protocol)
    if config.plan is not None:
        from controllers.task_space import TaskSpaceControl

        return TaskSpaceControl(config, protocol)
    return CurvatureControl(config, protocol)
