"""Whole-arm planning of the planar arm in confined spaces (issue 12).

The thesis advances its six-segment "cylindrical actuator" arm through pipe-like sections by "a
sequence of constrained nonlinear optimisations over the arm's configuration that keep its
envelope inside the environment while advancing the tip, tolerating collisions rather than
preventing them". `plan_whole_arm` is that sequence: each step is one SLSQP problem over the
curvatures whose objective pulls the tip towards a point a little ahead along the channel's
centreline (so it follows the pipe instead of cutting corners) with a smoothness term on the
change, under the constraints that every sampled backbone point keeps `width / 2 + margin` from
the walls and that no curvature changes by more than a trust region. Where the clearance
constraints cannot be met, or can be met only by not advancing (a pipe narrower than the arm
plus its margins), the step is solved again with a penalised slack on the clearance (the
collision is tolerated and reported in `Plan.slack_steps`) instead of failing or stalling.
The waypoints are then tracked by the curvature controllers as synchronised curvature moves
(robots.planar_arm.controller.tasks.CurvatureMove), which interpolate the curvatures linearly; so
each step is also checked along that interpolation and its trust region halved until the body
stays clear of the walls between waypoints too.

Why SLSQP: the problem is small (six curvatures, about fifty smooth inequality constraints with
analytic Jacobians, box bounds) and warm-started from the previous waypoint, where SQP's
superlinear convergence takes a handful of iterations. trust-constr (interior point) plans the
same waypoints but measured 5 to 8 times slower (pipe 1: 2.8 s against 0.35 s; pipe 4: 3.2 s
against 0.67 s), for no gain at this size.

The channel (walls, centreline, signed clearance) is robots.planar_arm.controller.confined's;
the sampled backbone points are the Environment FMU's (s = L k / n, k = 1..n per segment; the
base is clamped), so a plan with `clearance_min >= width / 2` is one the FMU sees without
penetration.

Invariant: every returned configuration lies within [lower, upper], consecutive configurations
differ by at most `step` per segment, and the plan is a deterministic function of its inputs (no
randomness; SLSQP is deterministic).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from controllers import kinematics
from robots.planar_arm.controller.confined import WIDTH, Channel

Floats = Sequence[float] | np.ndarray

SMALL_HALF_ANGLE = 1e-2  # [rad] below it sinc and its derivative take their series
FEASIBLE = 1e-7  # [m] constraint violation that still counts as met (SLSQP's rounding)
INTERPOLATION_CHECKS = (0.25, 0.5, 0.75)  # fractions of a step checked between waypoints
MAX_HALVINGS = 4  # trust-region halvings of one step before the interpolation check gives up
STALL_STEPS = 12  # steps without progress that end a plan as stalled
STALL_PROGRESS = 2e-4  # [m] progress that counts over STALL_STEPS


def sample_backbone(
    kappas: Floats, lengths: Floats, base: tuple[float, float, float], per_segment: int
) -> tuple[np.ndarray, np.ndarray]:
    """The Environment FMU's backbone points and their Jacobian on the curvatures.

    Points at s = L_j k / n (k = 1..n) on every segment j, the base excluded (it is clamped).

    Returns
    -------
    points, jacobian
        Positions, shape (N n, 2) [m], and d position / d kappa, shape (N n, 2, N) [m per 1/m]:
        as kinematics.point_jacobian, vectorised (segment i < j turns the point by L_i about
        the end of segment i and moves that end by its chord's derivative).
    """
    kappa = np.asarray(kappas, dtype=float)
    length = np.asarray(lengths, dtype=float)
    n_seg = len(length)
    joints = kinematics.forward(kappa, length, base)
    segment = np.repeat(np.arange(n_seg), per_segment)
    partial = length[segment] * np.tile(np.arange(1, per_segment + 1), n_seg) / per_segment
    start = joints[segment]
    chord, dchord = _chord(start[:, 2], kappa[segment], partial)
    points = start[:, :2] + chord
    # the last sample of each segment is its end: take forward()'s value, bit for bit
    points[per_segment - 1 :: per_segment] = joints[1:, :2]
    _, dfull = _chord(joints[:-1, 2], kappa, length)
    jacobian = np.zeros((len(points), 2, n_seg))
    for i in range(n_seg):
        distal = segment > i
        lever = points[distal] - joints[i + 1, :2]
        jacobian[distal, 0, i] = dfull[i, 0] - length[i] * lever[:, 1]
        jacobian[distal, 1, i] = dfull[i, 1] + length[i] * lever[:, 0]
        own = segment == i
        jacobian[own, :, i] = dchord[own]
    return points, jacobian


def _chord(heading: np.ndarray, kappa: np.ndarray, length: np.ndarray) -> tuple[np.ndarray, ...]:
    """Chord (end minus start) of arcs [m] and its derivative on the curvature [m^2]; see
    kinematics._chord_derivative (the same closed form and series, vectorised)."""
    half = 0.5 * kappa * length
    small = np.abs(half) < SMALL_HALF_ANGLE
    h = np.where(small, 1.0, half)  # a placeholder where the series is used
    h2 = half * half
    sinc = np.where(small, 1.0 - h2 / 6.0 * (1.0 - h2 / 20.0), np.sin(h) / h)
    dsinc = np.where(
        small,
        -half / 3.0 * (1.0 - h2 / 10.0 * (1.0 - h2 / 28.0)),
        (h * np.cos(h) - np.sin(h)) / (h * h),
    )
    direction = heading + half
    c, s = np.cos(direction), np.sin(direction)
    chord = np.stack((length * sinc * c, length * sinc * s), axis=-1)
    scale = 0.5 * length * length
    dchord = np.stack((scale * (dsinc * c - sinc * s), scale * (dsinc * s + sinc * c)), axis=-1)
    return chord, dchord


# ---------------------------------------------------------------------- planning


@dataclass(frozen=True)
class Plan:
    """A whole-arm plan: waypoints for the curvature controllers and how it went.

    Attributes
    ----------
    configurations
        Curvatures [1/m], each shape (N,), from the start (first) to the last waypoint.
    tip_path
        Tip position of each configuration, shape (len(configurations), 2) [m].
    clearance_min
        Smallest signed clearance [m] of any sampled backbone point (the capsule's axis) over
        all configurations: at least width / 2 means no penetration at the waypoints.
    reached
        Whether the last configuration puts the tip within the tolerance of the goal.
    reason
        Why the plan ended, one line.
    slack_steps
        Indices of the configurations whose clearance constraints could not be met and were
        relaxed (collisions tolerated); empty for a collision-free plan.
    """

    configurations: list[np.ndarray]
    tip_path: np.ndarray
    clearance_min: float
    reached: bool
    reason: str
    slack_steps: tuple[int, ...] = ()


@dataclass(frozen=True)
class _Problem:
    """What every step of one plan shares."""

    lengths: np.ndarray
    base: tuple[float, float, float]
    channel: Channel
    per_segment: int
    half_width: float  # [m] the capsule's radius
    required: float  # [m] clearance every sampled point must keep: width / 2 + margin
    lookahead: float  # [m]
    smoothness: float  # weight of the squared bend-angle change against (tip error / lookahead)^2

    def samples(self, kappa: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return sample_backbone(kappa, self.lengths, self.base, self.per_segment)

    def clearance(self, kappa: np.ndarray) -> np.ndarray:
        return self.channel.clearance(self.samples(kappa)[0])

    def tip(self, kappa: np.ndarray) -> np.ndarray:
        return kinematics.forward(kappa, self.lengths, self.base)[-1, :2]


def plan_whole_arm(
    start: Floats,
    goal: Floats,
    lengths: Floats,
    base: tuple[float, float, float],
    lower: Floats,
    upper: Floats,
    channel: Channel,
    *,
    width: float = WIDTH,
    margin: float = 2e-3,
    samples_per_segment: int = 8,
    step: float = 2.0,
    max_steps: int = 300,
    tolerance: float = 1e-3,
    lookahead: float = 0.02,
    smoothness: float = 0.05,
    slack_penalty: float = 100.0,
) -> Plan:
    """Plan a sequence of curvature configurations that advances the tip to `goal` through
    `channel`, one constrained optimisation (SLSQP) per step; see the module.

    Parameters
    ----------
    start
        Starting curvatures, shape (N,) [1/m], within [lower, upper].
    goal
        Tip goal (x, y) [m].
    lengths, base
        Segment arc lengths, shape (N,) [m]; base pose (x [m], y [m], heading [rad]).
    lower, upper
        Curvature bounds per segment, shape (N,) [1/m].
    channel
        The walls and the centreline the tip follows.
    width
        Diameter of the arm's capsule [m].
    margin
        Clearance kept beyond width / 2 at every sampled point [m].
    samples_per_segment
        Backbone points per segment (the Environment FMU's n_samples).
    step
        Trust region: the largest change of any curvature between waypoints [1/m].
    max_steps
        Largest number of steps (waypoints after the start).
    tolerance
        Tip distance from the goal that counts as reached [m].
    lookahead
        How far ahead of the tip's progress along the centreline the step's target lies [m].
    smoothness
        Weight of the squared change of the bend angles [1/rad^2] against the squared tip
        error in units of `lookahead`.
    slack_penalty
        Weight of the squared slack [m] against the squared tip error (both in units of
        `lookahead`) when the clearance constraints are relaxed: the slack is what a step adds
        to the shortfall the body already has (a tolerated collision may persist at no cost,
        deepening it costs). Relaxed only when the constraints are infeasible or the feasible
        step does not advance the tip.

    Returns
    -------
    Plan
        Never raises for an unreachable or infeasible goal: `reached` is False and `reason`
        says why. Raises ValueError for inconsistent inputs (shapes, bounds, a start outside
        them).
    """
    lengths_ = np.asarray(lengths, dtype=float)
    kappa = np.asarray(start, dtype=float).copy()
    lo = np.broadcast_to(np.asarray(lower, dtype=float), lengths_.shape).copy()
    hi = np.broadcast_to(np.asarray(upper, dtype=float), lengths_.shape).copy()
    goal_ = np.asarray(goal, dtype=float)
    if kappa.shape != lengths_.shape:
        raise ValueError(f"start: {kappa.size} curvatures for {lengths_.size} segments")
    if np.any(lo > hi):
        raise ValueError("lower/upper: a lower curvature bound exceeds its upper bound")
    if np.any(kappa < lo - 1e-12) or np.any(kappa > hi + 1e-12):
        raise ValueError("start: a curvature lies outside [lower, upper]")
    if goal_.shape != (2,):
        raise ValueError(f"goal: expected (x, y), got shape {goal_.shape}")
    if step <= 0.0 or width <= 0.0 or margin < 0.0 or lookahead <= 0.0:
        raise ValueError("step, width and lookahead must be positive and margin not negative")
    kappa = np.clip(kappa, lo, hi)
    problem = _Problem(
        lengths_,
        base,
        channel,
        samples_per_segment,
        0.5 * width,
        0.5 * width + margin,
        lookahead,
        smoothness,
    )
    configurations = [kappa.copy()]
    slack_steps: list[int] = []

    def finish(reached: bool, reason: str) -> Plan:
        tips = np.array([problem.tip(k) for k in configurations])
        clearance = min(float(np.min(problem.clearance(k))) for k in configurations)
        return Plan(configurations, tips, clearance, reached, reason, tuple(slack_steps))

    goal_clearance = float(channel.clearance(goal_[None])[0])
    if goal_clearance < 0.5 * width:
        where = "outside the channel" if goal_clearance < 0.0 else "too close to a wall"
        return finish(
            False,
            f"goal ({goal_[0]:.4f}, {goal_[1]:.4f}) m lies {where}: clearance "
            f"{goal_clearance:.4f} m < half the width {0.5 * width:.4f} m",
        )
    goal_progress = float(channel.progress(goal_[None])[0])
    best = (math.inf, -math.inf)  # (distance to goal, progress) at the last real advance
    since_advance = 0
    for index in range(1, max_steps + 1):
        tip = problem.tip(kappa)
        distance = float(np.linalg.norm(tip - goal_))
        if distance <= tolerance:
            return finish(True, f"reached the goal within {distance * 1e3:.2f} mm")
        progress = float(channel.progress(tip[None])[0])
        if distance < best[0] - STALL_PROGRESS or progress > best[1] + STALL_PROGRESS:
            best = (min(distance, best[0]), max(progress, best[1]))
            since_advance = 0
        else:
            since_advance += 1
            if since_advance >= STALL_STEPS:
                return finish(
                    False,
                    f"stalled {distance * 1e3:.1f} mm from the goal, {progress:.3f} of "
                    f"{goal_progress:.3f} m along the centreline: the goal is out of reach",
                )
        target = _target(channel, tip, goal_, progress, goal_progress, lookahead)
        kappa_next, slack = _step(problem, kappa, target, lo, hi, step, slack_penalty)
        if slack:
            slack_steps.append(index)
        kappa = kappa_next
        configurations.append(kappa.copy())
    distance = float(np.linalg.norm(problem.tip(kappa) - goal_))
    if distance <= tolerance:
        return finish(True, f"reached the goal within {distance * 1e3:.2f} mm")
    return finish(False, f"max_steps = {max_steps} ran out {distance * 1e3:.1f} mm from the goal")


def plan_penetration(plan: Plan, width: float) -> float:
    """Deepest penetration [m] of the capsule of `width` into a wall at the plan's waypoints
    (zero for a plan whose clearance_min is at least width / 2)."""
    return max(0.0, 0.5 * width - plan.clearance_min)


def _target(
    channel: Channel,
    tip: np.ndarray,
    goal: np.ndarray,
    progress: float,
    goal_progress: float,
    lookahead: float,
) -> np.ndarray:
    """The step's target: the centreline point `lookahead` ahead of the tip's progress, or the
    goal once it is within the lookahead."""
    if goal_progress - progress <= lookahead or float(np.linalg.norm(goal - tip)) <= lookahead:
        return goal
    return channel.point_at(progress + lookahead)[0]


def _step(
    problem: _Problem,
    kappa: np.ndarray,
    target: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    step: float,
    slack_penalty: float,
) -> tuple[np.ndarray, bool]:
    """One waypoint: the constrained optimum within the trust region, the trust region halved
    until the linear interpolation from `kappa` keeps the body clear; (curvatures, slacked)."""
    before = float(np.min(problem.clearance(kappa)))
    radius = step
    for _ in range(MAX_HALVINGS + 1):
        candidate, slacked = _optimise(problem, kappa, target, lo, hi, radius, slack_penalty)
        # between waypoints no sampled point may come closer than the capsule's radius (the
        # margin is what the interpolation may use up), nor, after a tolerated collision,
        # deeper than the body already was
        floor = min(problem.half_width, before)
        if all(
            float(np.min(problem.clearance(kappa + f * (candidate - kappa)))) >= floor - FEASIBLE
            for f in INTERPOLATION_CHECKS
        ):
            break
        radius *= 0.5
    return candidate, slacked


def _optimise(
    problem: _Problem,
    kappa: np.ndarray,
    target: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    radius: float,
    slack_penalty: float,
) -> tuple[np.ndarray, bool]:
    """SLSQP within the trust region `radius` [1/m]; with a slack variable on the clearance
    constraints when they cannot be met. Returns (curvatures, slacked)."""
    n = len(kappa)
    lower = np.maximum(lo, kappa - radius)
    upper = np.minimum(hi, kappa + radius)
    scale = 1.0 / problem.lookahead**2
    weight = problem.smoothness * problem.lengths**2
    cache: dict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}

    def evaluate(k: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        key = k.tobytes()
        if key not in cache:
            points, jacobian = problem.samples(k)
            clearance, gradient = problem.channel.clearance_and_gradient(points)
            cache.clear()  # SLSQP asks for one point at a time
            cache[key] = (
                points[-1],
                jacobian[-1],
                clearance,
                np.einsum("pk,pkn->pn", gradient, jacobian),
            )
        return cache[key]

    def objective(x: np.ndarray) -> tuple[float, np.ndarray]:
        k = x[:n]
        tip, tip_jacobian, _, _ = evaluate(k)
        error = tip - target
        change = k - kappa
        value = scale * float(error @ error) + float(weight @ (change * change))
        gradient = np.zeros_like(x)
        gradient[:n] = 2.0 * scale * (tip_jacobian.T @ error) + 2.0 * weight * change
        if len(x) > n:
            value += slack_penalty * scale * x[n] ** 2
            gradient[n] = 2.0 * slack_penalty * scale * x[n]
        return value, gradient

    # a tolerated collision may stay as deep as it already is at no cost; the slack is what
    # the step adds to it
    shortfall = max(0.0, -float(np.min(evaluate(kappa)[2] - problem.required)))

    def constraint(x: np.ndarray) -> np.ndarray:
        return evaluate(x[:n])[2] - problem.required

    def relaxed_constraint(x: np.ndarray) -> np.ndarray:
        return constraint(x) + shortfall + x[n]

    def constraint_jacobian(x: np.ndarray) -> np.ndarray:
        jacobian = evaluate(x[:n])[3]
        if len(x) > n:
            jacobian = np.hstack((jacobian, np.ones((len(jacobian), 1))))
        return jacobian

    constraints = {"type": "ineq", "fun": constraint, "jac": constraint_jacobian}
    relaxed_constraints = {"type": "ineq", "fun": relaxed_constraint, "jac": constraint_jacobian}
    result = minimize(
        objective,
        kappa,
        jac=True,
        method="SLSQP",
        bounds=list(zip(lower, upper, strict=True)),
        constraints=[constraints],
        options={"maxiter": 100, "ftol": 1e-10},
    )
    candidate = np.clip(result.x, lower, upper)
    feasible = float(np.min(constraint(candidate))) >= -FEASIBLE
    distance = float(np.linalg.norm(evaluate(kappa)[0] - target))
    advance = distance - float(np.linalg.norm(evaluate(candidate)[0] - target))
    if feasible and (advance >= STALL_PROGRESS or distance <= STALL_PROGRESS):
        return candidate, False
    # infeasible, or feasible only by not advancing (the body kept clear of a pipe narrower
    # than width + 2 margin by staying out of it): tolerate the collision, as little of it as
    # the penalty buys
    result = minimize(
        objective,
        np.append(kappa, 0.0),
        jac=True,
        method="SLSQP",
        bounds=[*zip(lower, upper, strict=True), (0.0, None)],
        constraints=[relaxed_constraints],
        options={"maxiter": 100, "ftol": 1e-10},
    )
    relaxed = np.clip(result.x[:n], lower, upper)
    relaxed_advance = distance - float(np.linalg.norm(evaluate(relaxed)[0] - target))
    if feasible and relaxed_advance < advance + STALL_PROGRESS:
        return candidate, False  # the collision would buy no advance
    return relaxed, float(np.min(constraint(relaxed))) < -FEASIBLE
