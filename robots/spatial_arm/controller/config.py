"""Everything the spatial arm's controller knows (controller.json): the arm's model parameters
(ArmBody's names and values), its timing, its task and the loops' gains. Angles in rad."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass

from controllers.config import CameraTiming, config_from_json

TASKS = ("configuration", "point", "object", "shape", "confined")
ESTIMATORS = ("kf", "ik")


@dataclass(frozen=True)
class SpatialConfig:
    robot: str
    control_period: float
    cycles: int
    camera_timing: CameraTiming  # 3-D markers: the base, every endplate, the object
    segments: int
    body: tuple[tuple[str, float], ...]  # ArmBody parameters by name (the model's values)
    start: tuple[float, ...]  # the bends the arm starts at rest on (theta_x_1, theta_y_1, ...)
    task: str = "point"
    estimator: str = "kf"
    goals: tuple[tuple[float, float, float], ...] = ()  # point: tip goals in the base frame
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)  # object: the tip's goal from it
    curve: tuple[tuple[float, float, float], ...] = ()  # shape: the curve's points
    bends: tuple[tuple[float, ...], ...] = ()  # configuration: [time, theta_x_1, ...] steps
    pipe: tuple[tuple[float, float, float], ...] = ()  # confined: the axis from the entrance
    pipe_radius: float = 0.0  # [m]
    goal_depth: float = 0.0  # [m] past the entrance along the axis
    width: float = 0.03  # [m] the arm's width
    clearance: float = 0.002  # [m] kept from the wall by the plan
    insertion_step: float = 0.02  # [m] of tip advance between the plan's stations
    tolerance: float = 2e-3  # [m] tip (or shape) error estimate within it: on target
    settle_time: float = 0.5  # [s] on target this long: settled
    max_time: float = 8.0  # [s] a goal not settled by then is given up
    speed: float = 0.5  # [rad/s] the largest bend rate of a trapezoidal move
    acceleration: float = 1.0  # [rad/s^2]
    kp: float = 0.0  # proportional gain, as a share of the static piston per bend
    ki: float = 0.0  # [1/s] integral gain, likewise
    x_min: float = 0.0  # [m] the piston range the controller commands
    x_max: float = 0.1
    camera_noise: float = 5e-4  # [m] marker noise (standard deviation)
    dropout: float = 0.0  # the camera's dropout rate (the estimator's gating)
    policy: str = "strict"
    timeout: float = 10.0

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> SpatialConfig:
        """Read a config; wrong or missing keys raise ValueError naming the key."""
        config: SpatialConfig = config_from_json(cls, text)
        if config.task not in TASKS:
            raise ValueError(f"task: {config.task!r} is not one of {', '.join(TASKS)}")
        if config.estimator not in ESTIMATORS:
            raise ValueError(
                f"estimator: {config.estimator!r} is not one of {', '.join(ESTIMATORS)}"
            )
        if not 1 <= config.segments <= 8:
            raise ValueError(f"segments: must be 1..8, got {config.segments}")
        if len(config.start) != 2 * config.segments:
            raise ValueError(f"start: needs {2 * config.segments} bends, got {len(config.start)}")
        if config.control_period <= 0 or config.cycles < 0 or config.timeout <= 0:
            raise ValueError("control_period and timeout must be positive, cycles not negative")
        if not config.x_min < config.x_max:
            raise ValueError("x_min: must be below x_max")
        return config

    @property
    def parameters(self) -> dict[str, float]:
        return dict(self.body)
