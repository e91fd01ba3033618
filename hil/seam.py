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

from controllers import cukf, kinematics
from controllers.config import ESTIMATORS, POLICIES, read_config
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

__all__ = [
    "ESTIMATORS",
    "ArmConfig",
    "POLICIES",
    "CameraAssembler",
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
