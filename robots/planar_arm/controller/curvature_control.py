"""The planar arm's curvature control: one curvature PI per segment (the outer loop of the
cascade; the drive's position servo is the inner one; on a multibody arm the PIs coupled by
its inertia, `controllers.curvature.ArmGains`), answering each cycle with a DriveCommand
and a ControllerState frame per segment (the reference it tracks and the estimate it used).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from controllers.curvature import CurvaturePI
from controllers.estimation import DriveReading, Estimate
from rigbus.protocol import ControllerState, DriveCommand, Protocol
from robots.planar_arm.controller.config import ControllerConfig

if TYPE_CHECKING:
    from controllers.kinematics import Floats


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
        motion: tuple[Floats, Floats] | None = None,
    ) -> list[Any]:
        """Each segment's PI towards its curvature reference: a DriveCommand and a
        ControllerState frame per segment. `motion`: the references' rate and acceleration
        where they follow a planned move (a multibody arm's loops feed them forward)."""
        frames: list[Any] = []
        lo, hi = self.shown_range
        arm = self.config.arm_gains  # the loops of a multibody arm: coupled through its inertia
        if arm is not None:
            errors = [float(r) - float(k) for r, k in zip(references, estimate.kappa, strict=True)]
            terms = arm.terms(list(estimate.kappa), errors, list(estimate.kappa_rate), motion)
        for i, pi in enumerate(self.pis):
            node = i + 1
            kappa_ref = float(references[i])
            reading = drives.get(node)
            piston = reading.piston_position if reading is not None else None
            kappa_est = float(estimate.kappa[i])
            if arm is None:
                setpoint = pi.update(kappa_ref, kappa_est, piston)
            else:
                setpoint = pi.update_terms(kappa_ref, *terms[i], piston)
            frames.append(DriveCommand(node, setpoint, True, cycle))
            frames.append(ControllerState(node, kappa_ref, min(max(kappa_est, lo), hi), cycle))
        return frames
