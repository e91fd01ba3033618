"""Task-space inverse kinematics of the planar PCC arm (controllers/kinematics.py) on its
curvatures.

Invariant: every curvature this module returns lies inside the given per-segment bounds [lower,
upper] (in practice `SegmentModel.reachable_curvature()`, the segment physics at full stroke).

Why damped least squares (DLS), not the Jacobian transpose nor the pseudo-inverse: a straight
planar arm is a singular configuration of the position Jacobian. Bending any segment moves the
tip sideways only, so every column is parallel to the arm's normal and the 2 x N Jacobian has
rank 1. The pseudo-inverse then divides by a singular value that tends to zero as the arm
straightens, and its steps blow up near the singularity; the transpose J^T e stays bounded but
scales the step with J^T J, so it crawls wherever a singular value is small (and its gain needs
tuning against the largest one). DLS, d theta = J^T (J J^T + lambda^2 I)^-1 e, is well-posed at
the singularity (each singular direction gets sigma / (sigma^2 + lambda^2) <= 1 / (2 lambda)) and
is Gauss-Newton, quadratically convergent for this under-determined problem, where lambda = 0.
The damping is variable (Maciejewski & Klein 1988): lambda^2 = damping^2 (1 - (sigma_min /
damping)^2) while the smallest singular value sigma_min < damping, else 0, so it acts only near a
singularity.

Method. The variables are the bend angles theta_i = kappa_i L_i [rad], so segments of different
lengths weigh alike and the damping has one unit [m]; the task is the tip position, optionally
with the heading error weighted by `heading_weight` [m/rad] (default: the mean segment length).
Redundancy (N curvatures for 2 or 3 task coordinates): each step adds a Newton step towards
`rest` (default: straight, the least bending) within the null space Z of the task Jacobian: the
sequential quadratic programming step of min ||theta - theta_rest||^2 / 2 subject to tip =
target, with the Lagrangian Hessian I - sum mu_k H_k (H_k the tip's exact Hessians,
`kinematics.tip_derivatives`, mu the least-squares multipliers) reduced to Z, its eigenvalues
taken in magnitude and floored so that the step stays a bounded descent direction. (The plain
projection (I - J^+ J)(theta_rest - theta) ignores the curvature of the solution set and can
cycle between two configurations.) A converged answer is therefore a stationary point of the
least-bending problem: unique within its basin (a start bent the opposite way may settle on the
mirrored S-shape), moving continuously with the target when warm-started. Tikhonov
regularisation towards rest would instead leave a residual task error. `rest_weight` scales the
null-space step (0: none).

Globalisation: while the target is not met, a step is kept only if the task error falls (a
large-residual Gauss-Newton step can overshoot): the full step if it at least halves the error,
else the task step alone, halved until it lowers the error. Each step is limited to
MAX_BEND_STEP per segment.

Bounds: an active set. Segments at a bound that the step would push outwards are held there and
their columns removed, and the step recomputed until none is; a step that crosses a bound is
clamped to it. A target needing more than the bounds ends with segments saturated and
`converged` False, its remaining error reported.

First-order stall: a straight arm and a target straight ahead, nearer than the arm's length, make
the error orthogonal to every column (J^T e = 0), so every first-order method stops there. The
solver then steps along the direction of most negative curvature of ||e||^2 / 2 (Hessian J^T J -
sum e_k H_k; bending in an S shortens the arm without moving the tip sideways to first order),
halved until the error falls; if there is none the point is a true local optimum (e.g. a target
beyond reach, straight ahead).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from controllers.kinematics import Floats, forward, tip_derivatives

DAMPING = 0.01  # [m] largest DLS damping, reached at a singularity
MAX_ITER = 100  # solve_ik's iterations unless told otherwise
MAX_BEND_STEP = 0.5  # [rad] largest bend-angle change per segment in one solver iteration
REACHED = 1e-9  # [m] ik_step tries no stall escape for a smaller (weighted) error
STATIONARY = 1e-9  # [rad] a solver step this small (per segment) means the iterate has settled
RCOND = 1e-9  # singular values below this share of the largest count as zero (null space)
LINE_SEARCH = 30  # tries (halving each time) before a step counts as no descent
REDUCED_CURVATURE_FLOOR = 0.1  # smallest curvature of the rest objective the Newton step assumes


@dataclass(frozen=True)
class IkResult:
    """Outcome of `solve_ik`.

    Attributes
    ----------
    kappas
        Curvatures, shape (N,) [1/m], within the bounds.
    position_error
        Distance from the tip to the target [m].
    heading_error
        Target heading minus tip heading, wrapped to [-pi, pi] [rad]; 0 when no heading was asked.
    iterations
        Solver iterations taken.
    converged
        The tip is within `tol` of the target (and within `heading_tol` of the heading if asked).
    saturated
        Shape (N,), True for each segment held at one of its bounds.
    """

    kappas: np.ndarray
    position_error: float
    heading_error: float
    iterations: int
    converged: bool
    saturated: np.ndarray


@dataclass(frozen=True)
class _Task:
    """The tip task in bend-angle variables: target pose and the heading row's weight."""

    lengths: np.ndarray  # [m]
    base: tuple[float, float, float]
    target: np.ndarray  # (x, y) [m]
    heading: float | None  # [rad]
    heading_weight: float  # [m/rad]

    def tip(self, theta: np.ndarray) -> np.ndarray:
        return forward(theta / self.lengths, self.lengths, self.base)[-1]

    def error(self, tip: np.ndarray) -> np.ndarray:
        """Weighted task error: position [m], then heading times heading_weight [m]."""
        position = self.target - tip[:2]
        if self.heading is None:
            return position
        wrapped = math.remainder(self.heading - float(tip[2]), 2.0 * math.pi)
        return np.append(position, self.heading_weight * wrapped)

    def evaluate(self, theta: np.ndarray) -> _Local:
        """Tip, error, Jacobian and position Hessian at bend angles `theta`."""
        tip, jacobian, hessian = tip_derivatives(theta / self.lengths, self.lengths, self.base)
        # d / d theta_i = (d / d kappa_i) / L_i
        jacobian = jacobian / self.lengths
        hessian = hessian / np.outer(self.lengths, self.lengths)
        if self.heading is not None:
            jacobian[2] *= self.heading_weight
        else:
            jacobian = jacobian[:2]
        return _Local(tip, self.error(tip), jacobian, hessian)


@dataclass(frozen=True)
class _Local:
    """The task linearised (and its curvature) at one configuration, in bend angles."""

    tip: np.ndarray  # (x, y, heading)
    error: np.ndarray  # weighted task error [m]
    jacobian: np.ndarray  # weighted task rows [m/rad]
    hessian: np.ndarray  # (2, N, N) of the tip position [m/rad^2]


def _step(
    local: _Local,
    theta: np.ndarray,
    free: np.ndarray,
    theta_rest: np.ndarray,
    damping: float,
    rest_weight: float,
) -> np.ndarray:
    """One step [rad] on the free segments: DLS towards the task plus a Newton step towards
    rest in the task's null space (see the module docstring)."""
    step = np.zeros_like(theta)
    if not free.any():
        return step
    jacobian = local.jacobian[:, free]
    u, sigma, vt = np.linalg.svd(jacobian, full_matrices=True)
    smallest = float(sigma[-1]) if sigma.size == jacobian.shape[0] else 0.0
    lam2 = damping * damping - smallest * smallest if smallest < damping else 0.0
    rank = int(np.sum(sigma > RCOND * max(float(sigma[0]), np.finfo(float).tiny)))
    u_r, sigma_r, v_r = u[:, :rank], sigma[:rank], vt[:rank].T
    primary = v_r @ (sigma_r / (sigma_r**2 + lam2) * (u_r.T @ local.error))
    null = vt[rank:].T
    if null.shape[1] == 0 or rest_weight == 0.0:
        step[free] = primary
        return step
    # Lagrangian Hessian of 1/2 ||theta - rest||^2 subject to the task: identity minus the
    # multipliers times the task's curvature (least-squares multipliers J^T mu = gradient)
    gradient = (theta - theta_rest)[free]
    multipliers = u_r @ ((v_r.T @ gradient) / sigma_r)
    curvature = local.hessian[:, free][:, :, free]
    lagrangian = np.eye(int(free.sum())) - np.tensordot(multipliers[:2], curvature, axes=1)
    reduced = null.T @ lagrangian @ null
    values, vectors = np.linalg.eigh(0.5 * (reduced + reduced.T))
    # a modified Newton step: where the rest objective curves down (or barely up) along the
    # solution set, a floor keeps the step a bounded descent direction
    values = np.maximum(np.abs(values), REDUCED_CURVATURE_FLOOR)
    rhs = null.T @ (lagrangian @ primary + gradient)
    secondary = -null @ (vectors @ ((vectors.T @ rhs) / values))
    step[free] = primary + rest_weight * secondary
    return step


def _held(theta: np.ndarray, lo: np.ndarray, hi: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Segments at a bound that the step would push beyond it."""
    return ((theta <= lo) & (step < 0.0)) | ((theta >= hi) & (step > 0.0))


def _active_step(
    local: _Local,
    theta: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    theta_rest: np.ndarray,
    damping: float,
    rest_weight: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The step with the segments held that it would push beyond a bound, and the mask of the
    free segments: starting from all free, segments at a bound that the step pushes outwards
    are held and the step recomputed, until none is (at most N passes)."""
    free = np.ones_like(theta, dtype=bool)
    while True:
        step = _step(local, theta, free, theta_rest, damping, rest_weight)
        held = _held(theta, lo, hi, step) & free
        if not held.any():
            return step, free
        free &= ~held


def _escape(
    task: _Task, local: _Local, theta: np.ndarray, free: np.ndarray, limit: float
) -> np.ndarray | None:
    """Where the first-order step vanishes but the error does not: a step along the direction
    of most negative curvature of 1/2 ||e||^2, whose Hessian there is J^T J - sum e_k H_k
    (H_k the tip's Hessians), halved until it lowers the error; None at a true local minimum
    (see the module docstring)."""
    if not free.any():
        return None
    current = float(np.linalg.norm(local.error))
    jacobian = local.jacobian[:, free]
    curvature = local.hessian[:, free][:, :, free]
    hessian = jacobian.T @ jacobian - np.tensordot(local.error[:2], curvature, axes=1)
    values, vectors = np.linalg.eigh(0.5 * (hessian + hessian.T))
    if not values[0] < 0.0:
        return None
    size = min(current / math.sqrt(-values[0]), limit)
    for _ in range(30):
        for sign in (1.0, -1.0):
            step = np.zeros_like(theta)
            step[free] = sign * size * vectors[:, 0]
            if np.linalg.norm(task.error(task.tip(theta + step))) < current:
                return step
        size *= 0.5
    return None


def _limited(step: np.ndarray, limit: float) -> np.ndarray:
    """The step scaled down, direction kept, to at most `limit` per segment [rad]."""
    largest = float(np.max(np.abs(step), initial=0.0))
    return step * (limit / largest) if largest > limit else step


def _descend(
    task: _Task,
    theta: np.ndarray,
    step: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    below: float,
    halvings: int = LINE_SEARCH,
) -> np.ndarray | None:
    """theta + step (limited, clamped to the bounds), halved until the task error falls below
    `below`; None if it does not within `halvings` tries."""
    step = _limited(step, MAX_BEND_STEP)
    if float(np.max(np.abs(step), initial=0.0)) <= STATIONARY:
        return None
    for _ in range(halvings):
        candidate = np.clip(theta + step, lo, hi)
        if float(np.linalg.norm(task.error(task.tip(candidate)))) < below:
            return candidate
        step = 0.5 * step
    return None


def _bounds(lengths: np.ndarray, lower: Floats, upper: Floats) -> tuple[np.ndarray, np.ndarray]:
    """Bend-angle bounds [rad] from curvature bounds [1/m], checked."""
    lo, hi = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    if lo.shape != lengths.shape or hi.shape != lengths.shape:
        raise ValueError(
            f"bounds of {lo.size} and {hi.size} segments for {lengths.size} segment lengths"
        )
    lo, hi = lo * lengths, hi * lengths
    if not np.all(lo <= hi):
        bad = int(np.argmax(~(lo <= hi)))
        raise ValueError(f"segment {bad}: lower curvature bound above the upper bound")
    return lo, hi


def _rest_angles(
    rest: Floats | None, lengths: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    if rest is None:
        return np.clip(np.zeros_like(lengths), lo, hi)
    return np.clip(np.asarray(rest, dtype=float) * lengths, lo, hi)


def solve_ik(
    target: Floats,
    initial: Floats,
    lengths: Floats,
    base: tuple[float, float, float],
    lower: Floats,
    upper: Floats,
    *,
    heading: float | None = None,
    heading_weight: float | None = None,
    damping: float = DAMPING,
    rest: Floats | None = None,
    rest_weight: float = 1.0,
    tol: float = 1e-6,
    heading_tol: float = 1e-6,
    max_iter: int = MAX_ITER,
) -> IkResult:
    """Curvatures that put the tip on `target` (and optionally at `heading`) within bounds.

    Parameters
    ----------
    target
        Tip position (x, y) [m].
    initial
        Starting curvatures, shape (N,) [1/m] (clamped into the bounds).
    lengths
        Segment arc lengths, shape (N,) [m].
    base
        Base pose (x [m], y [m], heading [rad]).
    lower, upper
        Per-segment curvature bounds, shape (N,) [1/m].
    heading
        Target tip heading [rad] (compared modulo 2 pi), or None for position only.
    heading_weight
        Metres that one radian of heading error counts as [m/rad]; default the mean length.
    damping
        Largest DLS damping, reached at a singularity [m].
    rest
        Curvatures the redundancy is resolved towards [1/m]; default zero (least bending).
    rest_weight
        Scale of the null-space Newton step towards `rest` (1: the full SQP step; 0: none,
        the answer then depends on the start).
    tol, heading_tol
        Convergence tolerances on the position [m] and heading [rad] errors.
    max_iter
        Largest number of iterations.

    Returns
    -------
    IkResult
        After the task is met the iteration continues until the step towards rest settles
        (below STATIONARY per segment) or `max_iter`; the returned curvatures are the last
        iterate that met the task, if any did.
    """
    lengths_ = np.asarray(lengths, dtype=float)
    lo, hi = _bounds(lengths_, lower, upper)
    theta = np.clip(np.asarray(initial, dtype=float) * lengths_, lo, hi)
    if theta.shape != lengths_.shape:
        raise ValueError(f"{theta.size} initial curvatures for {lengths_.size} segment lengths")
    weight = float(np.mean(lengths_)) if heading_weight is None else heading_weight
    task = _Task(lengths_, base, np.asarray(target, dtype=float), heading, weight)
    theta_rest = _rest_angles(rest, lengths_, lo, hi)

    def met(tip: np.ndarray) -> bool:
        position = float(np.linalg.norm(task.target - tip[:2]))
        if heading is None:
            return position <= tol
        wrapped = abs(math.remainder(heading - float(tip[2]), 2.0 * math.pi))
        return position <= tol and wrapped <= heading_tol

    last_met: np.ndarray | None = None
    iterations = 0
    while iterations < max_iter:
        local = task.evaluate(theta)
        task_met = met(local.tip)
        if task_met:
            last_met = theta.copy()
        step, free = _active_step(local, theta, lo, hi, theta_rest, damping, rest_weight)
        if task_met:
            # polishing towards rest along the solution set; done when it has settled
            if float(np.max(np.abs(step), initial=0.0)) <= STATIONARY:
                break
            theta = np.clip(theta + _limited(step, MAX_BEND_STEP), lo, hi)
        else:
            # towards the target the error must fall (the trust region alone lets a
            # large-residual Gauss-Newton step overshoot): the step with the pull to rest if it
            # at least halves the error, else the task step alone, halved until the error
            # falls, else the stall escape
            current = float(np.linalg.norm(local.error))
            candidate = _descend(task, theta, step, lo, hi, 0.5 * current, halvings=1)
            if candidate is None:
                primary, free = _active_step(local, theta, lo, hi, theta_rest, damping, 0.0)
                candidate = _descend(task, theta, primary, lo, hi, current)
            if candidate is None:
                escape = _escape(task, local, theta, free, MAX_BEND_STEP)
                if escape is None:
                    break
                candidate = np.clip(theta + escape, lo, hi)
            theta = candidate
        iterations += 1
    else:
        if met(task.tip(theta)):
            last_met = theta
    if last_met is not None:
        theta = last_met
    tip = task.tip(theta)
    heading_error = 0.0 if heading is None else math.remainder(heading - tip[2], 2.0 * math.pi)
    return IkResult(
        kappas=theta / lengths_,
        position_error=float(np.linalg.norm(task.target - tip[:2])),
        heading_error=float(heading_error),
        iterations=iterations,
        converged=last_met is not None,
        saturated=(theta <= lo) | (theta >= hi),
    )


def ik_step(
    kappas: Floats,
    position_error: Floats,
    lengths: Floats,
    base: tuple[float, float, float],
    lower: Floats,
    upper: Floats,
    *,
    heading_error: float | None = None,
    heading_weight: float | None = None,
    damping: float = DAMPING,
    rest: Floats | None = None,
    rest_weight: float = 1.0,
    max_step: float | Floats | None = None,
) -> np.ndarray:
    """One DLS step from `kappas` towards a task-space error: the next curvatures [1/m].

    The controller calls it every control cycle with the estimated curvatures and the error of
    the estimated tip pose, closing the loop through the plant instead of iterating a model.

    Parameters
    ----------
    kappas
        Current curvatures, shape (N,) [1/m]; the Jacobian is taken here.
    position_error
        Target minus tip position (x, y) [m].
    lengths, base, lower, upper, heading_weight, damping, rest, rest_weight
        As in `solve_ik`.
    heading_error
        Target minus tip heading [rad] (wrapped here), or None for position only.
    max_step
        Largest curvature change per segment in this step [1/m], scalar or shape (N,): the
        whole step is scaled down to respect it (its direction kept); None for no limit.

    Returns
    -------
    numpy.ndarray
        Curvatures, shape (N,) [1/m], within the bounds.
    """
    lengths_ = np.asarray(lengths, dtype=float)
    lo, hi = _bounds(lengths_, lower, upper)
    theta = np.clip(np.asarray(kappas, dtype=float) * lengths_, lo, hi)
    if theta.shape != lengths_.shape:
        raise ValueError(f"{theta.size} curvatures for {lengths_.size} segment lengths")
    weight = float(np.mean(lengths_)) if heading_weight is None else heading_weight
    tip = forward(theta / lengths_, lengths_, base)[-1]
    # the target implied by the error, so that the stall escape can evaluate the error
    target = tip[:2] + np.asarray(position_error, dtype=float)
    heading = None if heading_error is None else float(tip[2]) + heading_error
    task = _Task(lengths_, base, target, heading, weight)
    local = task.evaluate(theta)
    theta_rest = _rest_angles(rest, lengths_, lo, hi)
    step, free = _active_step(local, theta, lo, hi, theta_rest, damping, rest_weight)
    stalled = float(np.max(np.abs(step), initial=0.0)) <= STATIONARY
    if stalled and float(np.linalg.norm(local.error)) > REACHED:
        escape = _escape(task, local, theta, free, MAX_BEND_STEP)
        if escape is None:
            return theta / lengths_
        step = escape
    elif stalled:
        return theta / lengths_
    delta = step / lengths_
    if max_step is not None:
        limit = np.broadcast_to(np.asarray(max_step, dtype=float), delta.shape)
        if np.any(limit < 0.0):
            raise ValueError("max_step must not be negative")
        ratio = float(np.max(np.abs(delta) / np.where(limit > 0.0, limit, np.finfo(float).tiny)))
        if ratio > 1.0:
            delta = delta / ratio
    return np.clip((theta + delta * lengths_) / lengths_, lo / lengths_, hi / lengths_)


def sample_workspace(
    rng: np.random.Generator,
    lengths: Floats,
    base: tuple[float, float, float],
    lower: Floats,
    upper: Floats,
    n: int,
    margin: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Reachable tip poses, drawn by drawing curvatures uniformly inside the bounds shrunk by
    `margin` (a share of each range at each end, in [0, 0.5)).

    Returns
    -------
    poses, kappas
        Tip poses (x [m], y [m], heading [rad]), shape (n, 3), and the curvatures that reach
        them, shape (n, N) [1/m].
    """
    if not 0.0 <= margin < 0.5:
        raise ValueError(f"margin = {margin} must lie in [0, 0.5)")
    lengths_ = np.asarray(lengths, dtype=float)
    lo, hi = _bounds(lengths_, lower, upper)
    lo, hi = lo / lengths_, hi / lengths_
    span = hi - lo
    kappas = rng.uniform(lo + margin * span, hi - margin * span, size=(n, lengths_.size))
    poses = np.array([forward(k, lengths_, base)[-1] for k in kappas]).reshape(n, 3)
    return poses, kappas


def reachable(
    target: Floats,
    lengths: Floats,
    base: tuple[float, float, float],
    lower: Floats,
    upper: Floats,
    tol: float = 1e-6,
) -> bool:
    """Whether some curvatures within the bounds put the tip within `tol` [m] of `target`.

    Decided by `solve_ik` from three starts (rest, and halfway to each bound): True is a
    certificate; False means none of them reached it (the IK is local, so not a proof)."""
    lo = np.asarray(lower, dtype=float)
    hi = np.asarray(upper, dtype=float)
    distance = math.hypot(target[0] - base[0], target[1] - base[1])
    if distance > math.fsum(lengths) + tol:
        return False  # no bending makes the arm longer than its arc length
    starts = (np.zeros_like(lo), 0.5 * hi, 0.5 * lo)
    return any(
        solve_ik(target, start, lengths, base, lo, hi, tol=tol).converged for start in starts
    )
