"""Task-space tasks of the planar arm (issue 11): point-to-point targets and straight-line paths.

Both programs use this module: the plant draws a task's targets or paths from the scenario's seed
and scores the run against them; the controller is told them (controller.json) and pursues them.
Invariant: every random draw comes from the `numpy.random.Generator` passed in, so a scenario
and seed give the same targets on every machine.

Targets are drawn where the arm can reach them by construction: curvatures drawn uniformly within
a shrunk share (`margin`) of each segment's reachable range, mapped through the forward
kinematics; a candidate pool many times larger than the count is thinned by farthest-point
sampling, so the targets spread over the workspace instead of clustering where the uniform
curvature draw puts most tips (near the straight arm). Paths are straight lines whose every
point has an IK solution within the same shrunk ranges.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from controllers import kinematics
from controllers.kinematics import Floats
from rigbus.protocol import TASK_PHASES

PHASE = {name: code for code, name in enumerate(TASK_PHASES)}
TASK_KINDS = ("point_to_point", "path", "pipe", "grasp")
CANDIDATES_PER_TARGET = 32
PATH_ATTEMPTS = 200
PATH_CHECKS = 21  # points along a drawn path that must each have an IK solution


@dataclass(frozen=True)
class TaskPlan:
    """What the task-space controller pursues, and the arm's limits it must respect.

    `targets` are the point-to-point targets, or the paths' start points with `ends` their end
    points [m]. `kappa_min`/`kappa_max` [1/m] bound each segment's curvature reference (the
    reachable range from the segment's physics at full stroke, less a margin for the feedback to
    act in); `kappa_rate` [1/(m s)] bounds its rate (the drive's speed through the segment's
    curvature per piston travel)."""

    kind: str
    targets: tuple[tuple[float, float], ...]
    ends: tuple[tuple[float, float], ...] = ()
    kappa_min: tuple[float, ...] = ()
    kappa_max: tuple[float, ...] = ()
    kappa_rate: tuple[float, ...] = ()
    tolerance: float = 1e-3  # [m] estimated tip error that counts as on target
    settle_time: float = 0.5  # [s] on target this long: settled, next target
    max_time: float = 6.0  # [s] per target (or path) before giving up on it
    speed: float = 0.01  # [m/s] path speed
    acceleration: float = 0.02  # [m/s^2] path acceleration
    accel_time: float = 0.2  # [s] ramp of a curvature move from rest to its rate limit
    task_gain: float = 1.0  # [1/s] integral gain on the estimated tip error
    correction_limit: float = 5e-3  # [m] bound of the integrated task-space correction
    acquire_time: float = 0.2  # [s] the pistons held while the estimator acquires the arm
    # confined spaces (kind "pipe"): the channel the controller plans through, its map
    walls: tuple[tuple[tuple[float, float], ...], ...] = ()
    centreline: tuple[tuple[float, float], ...] = ()
    width: float = 0.0  # [m] the arm's backbone width
    clearance: float = 2e-3  # [m] kept beyond width / 2 by the plan
    # grasp-and-place (kind "grasp"): the object (found by the camera) goes to targets[0]
    object_radius: float = 0.0  # [m]
    grasp_time: float = 1.0  # [s] the fingers close (or open) this long before the arm moves on

    def legs(self) -> int:
        return len(self.targets)


def draw_targets(
    rng: np.random.Generator,
    lengths: Sequence[float],
    base: tuple[float, float, float],
    lower: Floats,
    upper: Floats,
    count: int,
    margin: float = 0.7,
) -> list[tuple[float, float]]:
    """`count` reachable tip targets spread over the workspace [m]."""
    lo, hi = _shrunk(lower, upper, margin)
    pool = rng.uniform(lo, hi, size=(CANDIDATES_PER_TARGET * count, len(lengths)))
    tips = np.array([kinematics.forward(k, lengths, base)[-1, :2] for k in pool])
    chosen = [0]
    distance = np.linalg.norm(tips - tips[0], axis=1)
    while len(chosen) < count:
        nxt = int(np.argmax(distance))
        chosen.append(nxt)
        distance = np.minimum(distance, np.linalg.norm(tips - tips[nxt], axis=1))
    return [(float(tips[i, 0]), float(tips[i, 1])) for i in chosen]


def draw_paths(
    rng: np.random.Generator,
    lengths: Sequence[float],
    base: tuple[float, float, float],
    lower: Floats,
    upper: Floats,
    count: int,
    length: float,
    margin: float = 0.7,
) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    """`count` straight paths of `length` [m] whose every point the arm reaches within the
    shrunk curvature ranges (checked by IK at PATH_CHECKS points)."""
    from robots.planar_arm.controller.ik import solve_ik

    lo, hi = _shrunk(lower, upper, margin)
    paths = []
    for _ in range(count):
        for _attempt in range(PATH_ATTEMPTS):
            kappas = rng.uniform(lo, hi)
            start = kinematics.forward(kappas, lengths, base)[-1, :2]
            angle = rng.uniform(-math.pi, math.pi)
            end = start + length * np.array([math.cos(angle), math.sin(angle)])
            guess = kappas
            for s in np.linspace(0.0, 1.0, PATH_CHECKS):
                point = (1.0 - s) * start + s * end
                result = solve_ik(point, guess, lengths, base, lo, hi)
                if not result.converged:
                    break
                guess = result.kappas
            else:
                paths.append(((float(start[0]), float(start[1])), (float(end[0]), float(end[1]))))
                break
        else:
            raise ValueError(
                f"no straight path of {length:g} m fits the workspace in {PATH_ATTEMPTS} draws"
            )
    return paths


def _shrunk(lower: Floats, upper: Floats, margin: float) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo) * margin
    return mid - half, mid + half


@dataclass(frozen=True)
class CurvatureMove:
    """A realisable move of every segment's curvature from `start` to `goal`: a trapezoidal rate
    profile per segment (ramps of `accel_time` to at most its rate limit), all segments scaled to
    the slowest one's duration so that they arrive together and the tip moves smoothly."""

    start: np.ndarray
    goal: np.ndarray
    duration: float
    ramp: float

    @classmethod
    def plan(
        cls, start: np.ndarray, goal: np.ndarray, rates: np.ndarray, accel_time: float
    ) -> CurvatureMove:
        # a trapezoid of peak rate r and ramps t_a covers r (D - t_a) in D: the slowest segment
        # sets D = |delta| / r + t_a
        delta = np.abs(goal - start)
        duration = float(np.max(delta / rates)) + accel_time if np.any(delta > 0.0) else 0.0
        return cls(start.copy(), goal.copy(), duration, min(accel_time, 0.5 * duration))

    def value(self, tau: float) -> np.ndarray:
        """The curvatures `tau` [s] after the move started."""
        return self.start + (self.goal - self.start) * trapezoid_fraction(
            tau, self.duration, self.ramp
        )

    def motion(self, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """The curvatures' rate [1/(m s)] and acceleration [1/(m s^2)] `tau` [s] after the move
        started (the trapezoid's, exactly)."""
        rate, acceleration = trapezoid_derivatives(tau, self.duration, self.ramp)
        delta = self.goal - self.start
        return delta * rate, delta * acceleration


def trapezoid_fraction(tau: float, duration: float, ramp: float) -> float:
    """Fraction 0..1 of a move of `duration` [s] covered at `tau` [s] with a trapezoidal
    velocity profile whose ramps last `ramp` [s] each."""
    if duration <= 0.0 or tau >= duration:
        return 1.0
    if tau <= 0.0:
        return 0.0
    peak = 1.0 / (duration - ramp)  # the area of the trapezoid is 1
    if tau < ramp:
        return 0.5 * peak * tau * tau / ramp
    if tau <= duration - ramp:
        return peak * (tau - 0.5 * ramp)
    rest = duration - tau
    return 1.0 - 0.5 * peak * rest * rest / ramp


def trapezoid_derivatives(tau: float, duration: float, ramp: float) -> tuple[float, float]:
    """The first and second time derivatives [1/s, 1/s^2] of `trapezoid_fraction`."""
    if duration <= 0.0 or tau <= 0.0 or tau >= duration:
        return 0.0, 0.0
    peak = 1.0 / (duration - ramp)
    if tau < ramp:
        return peak * tau / ramp, peak / ramp
    if tau <= duration - ramp:
        return peak, 0.0
    return peak * (duration - tau) / ramp, -peak / ramp


def path_timing(length: float, speed: float, acceleration: float) -> tuple[float, float]:
    """(duration, ramp) [s] of a trapezoidal traverse of `length` [m] at `speed` with
    `acceleration` (a triangle where the path is too short to reach the speed)."""
    ramp = speed / acceleration
    if ramp * speed >= length:  # triangle: accelerate half way, decelerate
        ramp = math.sqrt(length / acceleration)
        return 2.0 * ramp, ramp
    return length / speed + ramp, ramp


def point_to_segment(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance [m] of each point (shape (n, 2)) from the line segment a-b."""
    ab = b - a
    s = np.clip(((points - a) @ ab) / float(ab @ ab), 0.0, 1.0)
    return np.asarray(np.linalg.norm(points - (a + s[:, None] * ab), axis=1))
