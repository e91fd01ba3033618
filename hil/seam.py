"""The seam: everything the plant side (`hil`) takes from the controller side, in one place.

The plant's tools run a controller in this process (`hil run --inprocess`, `hil replay`), start
the controller program (`hil controller`), read and check its configuration, score its
estimators over a recorded run (`hil estimate`) and design its outer loop (`hil tune`). They
reach the controller side only here: a test checks the import graph. (The estimators' report
is the planar arm's: it reads the arm's configuration, `ArmConfig`.) The controller side never
imports the plant, and a robot kind's controller side is found through `rigbus.robots`.
Modules that are slow to import (python-control, filterpy) are imported where they are used.
"""

from __future__ import annotations

from types import ModuleType
from typing import TYPE_CHECKING

from controllers import cukf, kinematics
from controllers.config import ESTIMATORS, POLICIES, CameraTiming, read_config
from controllers.estimation import DriveReading, MarkerFrame
from controllers.node import (
    CameraAssembler,
    ControllerError,
    ControllerNode,
    LockstepClock,
    RealtimeClock,
)
from controllers.trajectories import CurvatureProfile, Sine
from robots.planar_arm.controller.config import ControllerConfig as ArmConfig

if TYPE_CHECKING:
    from hil.scenario import Scenario

__all__ = [
    "ESTIMATORS",
    "ArmConfig",
    "POLICIES",
    "CameraAssembler",
    "CameraTiming",
    "ControllerError",
    "ControllerNode",
    "CurvatureProfile",
    "DriveReading",
    "LockstepClock",
    "MarkerFrame",
    "RealtimeClock",
    "Sine",
    "controller_program",
    "cukf",
    "estimators",
    "kinematics",
    "loop_design",
    "read_config",
]


def estimators() -> ModuleType:
    """The arm's curvature estimators (`controllers.estimators`: filterpy)."""
    from controllers import estimators as module

    return module


def loop_design() -> ModuleType:
    """The outer loop's design (`controllers.loop_design`: python-control)."""
    from controllers import loop_design as module

    return module


def controller_program() -> ModuleType:
    """The controller program's command line (`python -m controllers`)."""
    from controllers import __main__ as module

    return module


def camera_timing(scenario: Scenario, markers: int, dims: int = 2) -> CameraTiming:
    """When the scenario's camera frames become available, as every robot kind's controller is
    told it: its period, latency and the control period in ticks, the latest a jittered exposure
    falls, and the markers a picture holds (`dims` 3 for 3-D markers)."""
    from hil.vision import exposure_delay_bound

    return CameraTiming(
        period_ticks=scenario.camera_ticks,
        latency_ticks=scenario.latency_ticks,
        control_ticks=scenario.control_ticks,
        delay_ticks=exposure_delay_bound(
            scenario.camera.jitter, scenario.camera_ticks, scenario.timing.step
        ),
        markers=markers,
        dims=dims,
    )
