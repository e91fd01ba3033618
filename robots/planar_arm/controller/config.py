"""The planar arm's controller configuration: everything its controller knows about the rig and
its task, written by `hil run` as controller.json and read back with every key, type and range
checked (ValueError naming the key).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass

from controllers.config import ESTIMATORS, CameraTiming, config_from_json
from controllers.curvature import ArmGains, PiGains
from controllers.estimation import BendModel, CameraNoise
from controllers.trajectories import CurvatureProfile, Sine
from robots.planar_arm.controller.gripper import GripperGeometry
from robots.planar_arm.controller.tasks import TASK_KINDS, TaskPlan

_ = Sine  # the profile's sine is read through config_from_json


@dataclass(frozen=True)
class GripperConfig:
    """The gripper's drive (node) and the piston positions [m] that start, open and close it."""

    node: int
    x_start: float
    x_open: float
    x_closed: float
    geometry: GripperGeometry = GripperGeometry()


@dataclass(frozen=True)
class ControllerConfig:
    """Everything the planar arm's controller knows about the rig and its task (written by
    `hil run` as controller.json); per-segment values are tuples, segment 1 first."""

    robot: str
    lengths: tuple[float, ...]
    base: tuple[float, float, float]
    control_period: float
    cycles: int
    x_mid: tuple[float, ...]
    x_min: tuple[float, ...]
    x_max: tuple[float, ...]
    gains: tuple[PiGains, ...]
    profile: CurvatureProfile
    bends: tuple[BendModel, ...]
    camera: CameraNoise
    camera_timing: CameraTiming
    feedforward: tuple[float, ...] = ()  # piston offset per unit curvature reference [m per 1/m]
    policy: str = "strict"
    timeout: float = 10.0  # wall-clock wait for a cycle's frames [s]
    estimator: str = "raw"
    latency_compensation: bool = True
    torque_std: float | None = None  # the estimator's unmodelled torque std [N m]; None: derived
    plan: TaskPlan | None = None  # task-space task (point-to-point, path); None: the profile
    objects: int = 0  # object markers the camera reports after the arm's (ids segments + 1 ...)
    gripper: GripperConfig | None = None  # the finger pair at the tip and its drive
    # the segments' masses [kg] where they are one multibody arm: the estimators predict the
    # bends coupled by its mass matrix (controllers.kinematics.mass_matrix); None: each alone
    masses: tuple[float, ...] | None = None
    # the curvature loops coupled through the arm's inertia (in place of `gains`); None: each
    # segment's own PI (`gains`)
    arm_gains: ArmGains | None = None

    @property
    def segments(self) -> int:
        return len(self.lengths)

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> ControllerConfig:
        """Read a config; wrong or missing keys raise ValueError naming the key."""
        config: ControllerConfig = config_from_json(cls, text)
        if config.estimator not in ESTIMATORS:
            raise ValueError(
                f"estimator: {config.estimator!r} is not one of {', '.join(ESTIMATORS)}"
            )
        n = config.segments
        for name in ("x_mid", "x_min", "x_max", "gains", "bends", "feedforward"):
            if len(getattr(config, name)) != n:
                raise ValueError(f"{name}: {len(getattr(config, name))} values for {n} segments")
        if config.control_period <= 0 or config.cycles < 0 or config.timeout <= 0:
            raise ValueError("control_period and timeout must be positive, cycles not negative")
        _check_ranges(config)
        if config.plan is not None:
            _check_plan(config.plan, n)
        return config


# The ranges `hil run` validates a scenario against (hil/scenario.py), for a config written by
# hand: control period 1 us .. 1 s, at most 10 million cycles, a wait of at most an hour, and
# gains within the DBC's piston range (0.1 m) per 0.01 1/m of curvature error.
CONTROL_PERIOD_RANGE = (1e-6, 1.0)
MAX_CYCLES = 10_000_000
MAX_TIMEOUT = 3_600.0
KP_MAX = 0.1 / 0.01


def _check_ranges(config: ControllerConfig) -> None:
    lo, hi = CONTROL_PERIOD_RANGE
    if not lo <= config.control_period <= hi:
        raise ValueError(f"control_period: {config.control_period:g} s is outside {lo:g}..{hi:g}")
    if config.cycles > MAX_CYCLES:
        raise ValueError(f"cycles: {config.cycles} is beyond {MAX_CYCLES}")
    if config.timeout > MAX_TIMEOUT:
        raise ValueError(f"timeout: {config.timeout:g} s is beyond {MAX_TIMEOUT:g} s")
    if any(length <= 0 for length in config.lengths):
        raise ValueError("lengths: must be positive")
    for i, gains in enumerate(config.gains):
        if not 0 <= gains.Kp <= KP_MAX:
            raise ValueError(f"gains[{i}].Kp: {gains.Kp:g} is outside 0..{KP_MAX:g}")
        if not 0 <= gains.Ki <= KP_MAX / config.control_period:
            raise ValueError(
                f"gains[{i}].Ki: {gains.Ki:g} is outside 0..{KP_MAX / config.control_period:g}"
            )
    timing = config.camera_timing  # its own ranges: CameraTiming.__post_init__
    if config.torque_std is not None and not config.torque_std > 0:
        raise ValueError(f"torque_std: must be positive, got {config.torque_std}")
    if config.objects < 0:
        raise ValueError("objects: must not be negative")
    if timing.markers != config.segments + 1 + config.objects:
        raise ValueError(
            f"camera_timing.markers: must be {config.segments + 1 + config.objects} "
            "(segments + 1 + objects)"
        )
    if config.gripper is not None and config.gripper.node <= config.segments:
        raise ValueError("gripper.node: must follow the segments' drives")


def _check_plan(plan: TaskPlan, segments: int) -> None:
    if plan.kind not in TASK_KINDS:
        raise ValueError(f"plan.kind: {plan.kind!r} is not one of {', '.join(TASK_KINDS)}")
    if not plan.targets:
        raise ValueError("plan.targets: no target")
    if plan.kind == "path" and len(plan.ends) != len(plan.targets):
        raise ValueError(f"plan.ends: {len(plan.ends)} ends for {len(plan.targets)} paths")
    for name in ("kappa_min", "kappa_max", "kappa_rate"):
        if len(getattr(plan, name)) != segments:
            raise ValueError(
                f"plan.{name}: {len(getattr(plan, name))} values for {segments} segments"
            )
    if any(lo >= hi for lo, hi in zip(plan.kappa_min, plan.kappa_max, strict=True)):
        raise ValueError("plan.kappa_min: must be below plan.kappa_max")
    for name in ("kappa_rate",):
        if any(v <= 0 for v in getattr(plan, name)):
            raise ValueError(f"plan.{name}: must be positive")
    for name in ("tolerance", "settle_time", "max_time", "speed", "acceleration", "accel_time"):
        if getattr(plan, name) <= 0:
            raise ValueError(f"plan.{name}: must be positive")
