"""The spatial arm's controller side, as the controller node runs it (`rigbus.robots`): its
configuration (`config_class`), its estimator (`make_estimator`: the bends from the camera's 3-D
markers, `estimator`), its controller (`make_controller`: IK, trapezoidal moves and the cascaded
loops, `control`), the status frames every cycle must bring (`expected`) and what the estimator
sees of them (`readings`). The arm's mathematics: `model`, `kinematics`, `statics`, `ik`,
`envelope`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from controllers.estimation import DriveReading
from rigbus.protocol import Protocol
from robots.spatial_arm.controller.config import SpatialConfig


def expected(config: SpatialConfig) -> set[tuple[str, int | None]]:
    """Every drive's status: two per segment."""
    return {("DriveStatus", n) for n in range(1, 2 * config.segments + 1)}


def readings(status: Mapping[tuple[str, int | None], Any]) -> dict[int, DriveReading]:
    """Each drive's reading by node, from the cycle's DriveStatus frames."""
    return {
        key[1]: DriveReading(s.piston_position, s.p_a, s.p_b, s.fault)
        for key, s in status.items()
        if key[0] == "DriveStatus" and key[1] is not None
    }


def _model(config: SpatialConfig) -> Any:
    from robots.spatial_arm.controller.model import ArmModel

    return ArmModel.from_fmu_parameters(config.parameters)


def make_estimator(config: SpatialConfig) -> Any:
    from robots.spatial_arm.controller.estimator import SpatialEstimator

    return SpatialEstimator(config, _model(config))


def make_controller(config: SpatialConfig, protocol: Protocol) -> Any:
    from robots.spatial_arm.controller.control import SpatialControl

    return SpatialControl(config, _model(config), protocol)


config_class = SpatialConfig
