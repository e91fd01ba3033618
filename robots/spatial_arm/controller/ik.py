"""Spatial inverse kinematics on the gravity-loaded arm: bends that put the tip at a goal (or the
backbone along a curve) and that the pistons can hold at rest.

A bend q is statically reachable when each pair's torque needed to hold it, (K q + G(q))_j
(statics.required_torque: bending stiffness plus gravity), lies within what its piston gives over
the stroke less a margin, tau(theta_j, margin) <= (K q + G(q))_j <= tau(theta_j, stroke -
margin) (the torque rises monotonically with the piston, so this is the piston's range), and
every segment within its limit, |theta_s| <= theta_max. Those are smooth inequality constraints
on q with analytic gradients (the gravity stiffness dG/dq, the gas torque's slope in theta).

`solve_ik` (scipy's SLSQP) runs two stages: first the nearest reachable tip, min |tip(q) -
goal|^2 / l^2 + w |q - q_ref|^2 under the constraints (l the arm's length, w = `regularisation`,
small: this stage finds the goal or the best approach to it); then, from there, the
least-bent way to the goal, min |q - q_ref|^2 subject to tip(q) = goal as an equality and the
same constraints (q_ref `prefer`, default straight: prefer small bends; pass the current q to
stay near it). A goal is reached when the tip is within `tolerance` of it; an unreachable one
returns the first stage's nearest reachable point with `success` False. The pistons are then
`statics.pistons_for(q)`, and `stable` says whether the rest they hold is a stable one (the
potential's Hessian positive definite), i.e. whether the arm would stay there. q is the arm's
rest at those pistons only where stable. The first stage starts from `start` (default
`prefer`), the second from the first's answer. Both are local: a refusal means no reachable
rest near the path from `start`; envelope.Envelope.start_for gives a start among the sampled
rests. Measured on the default arm: 30 of 30 goals drawn inside the envelope (1 cm margin)
reached within 2e-11 m, 0.25 s median and 0.5 s at most per goal, from straight or from the
nearest sampled rest alike.

`fit_shape`: the bends whose backbone best follows a 3-D curve from the base, min sum_k
|p_k(q) - c(s_k)|^2 over stations p_k along the arm (each segment's arc points and its endplate)
at arc lengths s_k from the base, c(s) the curve's point at the same arc length (a polyline
from the base, linearly interpolated, held at its end beyond it), under the same constraints.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from robots.spatial_arm.controller import gas, statics
from robots.spatial_arm.controller.kinematics import points, stations, tip_jacobian
from robots.spatial_arm.controller.model import ArmModel

MARGIN = 0.002  # [m] of the stroke kept at each end by default
TOLERANCE = 1e-6  # [m] a goal within this of the tip is reached
REGULARISATION = 1e-3  # the first stage's weight of |q - q_ref|^2 [rad^-2] against |e|^2 / l^2
# the second stage minimises BENDING_SCALE |q - q_ref|^2: only its scale against SLSQP's ftol
# matters (measured: scale 1 takes 50-230 iterations and up to 10 s where 0.01 takes 8-11)
BENDING_SCALE = 0.01
MAX_ITERATIONS = 300
FTOL_APPROACH = 1e-12
FTOL_EXACT = 1e-10
TORQUE_SCALE = 0.1  # [N m] the piston constraints' unit


@dataclass(frozen=True)
class IKResult:
    """q (n_q), the pistons holding it [m], the tip, its distance to the goal [m], reached
    (within tolerance and statically reachable), the rest's stability, and the solver's
    message."""

    q: np.ndarray
    pistons: np.ndarray
    tip: np.ndarray
    error: float
    success: bool
    stable: bool
    message: str


@dataclass(frozen=True)
class ShapeFit:
    """q (n_q), the pistons [m], the stations' rms and largest distance to the curve [m],
    the constraints met, stability, and the solver's message."""

    q: np.ndarray
    pistons: np.ndarray
    rms: float
    max_error: float
    success: bool
    stable: bool
    message: str


def constraints(model: ArmModel, margin: float = MARGIN) -> list[dict]:
    """SLSQP's inequality constraints (>= 0) of a statically reachable q: the bend limits and
    each pair's torque range over [margin, stroke - margin]."""
    if not 0.0 <= margin < 0.5 * model.stroke:
        raise ValueError(f"margin = {margin} m: outside [0, stroke / 2)")
    G_a = np.repeat(np.asarray(model.G_a), model.n_dof)
    low, high = margin, model.stroke - margin

    def limit(q: np.ndarray) -> np.ndarray:
        return model.theta_max**2 - np.sum(model.full(q) ** 2, axis=-1)

    def limit_jac(q: np.ndarray) -> np.ndarray:
        full = model.full(q)
        out = np.zeros((model.n_segments, model.n_segments, 2))
        out[np.arange(model.n_segments), np.arange(model.n_segments)] = -2.0 * full
        return model.reduce(out)

    def torque(q: np.ndarray) -> np.ndarray:
        need = statics.required_torque(model, q)
        lo, hi = gas.torque(model, G_a, q, low).tau, gas.torque(model, G_a, q, high).tau
        return np.concatenate([need - lo, hi - need]) / TORQUE_SCALE

    def torque_jac(q: np.ndarray) -> np.ndarray:
        need = model.stiffness * np.eye(model.n_q) + statics.gravity_stiffness(model, q)
        lo = np.diag(gas.torque(model, G_a, q, low).d_theta)
        hi = np.diag(gas.torque(model, G_a, q, high).d_theta)
        return np.vstack([need - lo, hi - need]) / TORQUE_SCALE

    return [
        {"type": "ineq", "fun": limit, "jac": limit_jac},
        {"type": "ineq", "fun": torque, "jac": torque_jac},
    ]


def _stable(model: ArmModel, q: np.ndarray, pistons: np.ndarray) -> bool:
    if not np.all(np.isfinite(pistons)):
        return False
    return bool(np.linalg.eigvalsh(statics.stiffness(model, q, pistons))[0] > 0.0)


def _run(
    objective: Callable[[np.ndarray], tuple[float, np.ndarray]],
    start: np.ndarray,
    cons: list[dict],
    ftol: float,
) -> tuple[np.ndarray, str]:
    result = minimize(
        objective,
        start,
        jac=True,
        method="SLSQP",
        constraints=cons,
        options={"maxiter": MAX_ITERATIONS, "ftol": ftol},
    )
    return np.asarray(result.x), str(result.message)


def _feasible(model: ArmModel, q: np.ndarray, cons: list[dict]) -> bool:
    return all(np.min(c["fun"](q)) >= -1e-9 for c in cons)


def solve_ik(
    model: ArmModel,
    goal: np.ndarray,
    start: np.ndarray | None = None,
    prefer: np.ndarray | None = None,
    margin: float = MARGIN,
    regularisation: float = REGULARISATION,
    tolerance: float = TOLERANCE,
) -> IKResult:
    """q putting the tip at `goal` (3,) [m] at a static rest within the pistons' stroke less
    `margin`: module docstring."""
    goal = np.asarray(goal, dtype=float)
    if goal.shape != (3,) or not np.all(np.isfinite(goal)):
        raise ValueError(f"goal: {goal!r} is not a finite 3-vector")
    ref = np.zeros(model.n_q) if prefer is None else np.asarray(prefer, dtype=float)
    q0 = ref.copy() if start is None else np.asarray(start, dtype=float)
    cons = constraints(model, margin)
    scale = 1.0 / model.length**2

    def approach(q: np.ndarray) -> tuple[float, np.ndarray]:
        p, J = tip_jacobian(model, q)
        e, d = p - goal, q - ref
        w = regularisation
        return float(scale * e @ e + w * d @ d), 2.0 * (scale * J.T @ e + w * d)

    def bending(q: np.ndarray) -> tuple[float, np.ndarray]:
        d = q - ref
        return float(BENDING_SCALE * d @ d), 2.0 * BENDING_SCALE * d

    def on_goal(q: np.ndarray) -> np.ndarray:
        return (tip_jacobian(model, q)[0] - goal) / model.length

    def on_goal_jac(q: np.ndarray) -> np.ndarray:
        return tip_jacobian(model, q)[1] / model.length

    q1, message = _run(approach, q0, cons, FTOL_APPROACH)
    best, best_error = q1, _distance(model, q1, goal)
    if best_error <= model.length:  # near enough for the exact stage to start from
        reach = {"type": "eq", "fun": on_goal, "jac": on_goal_jac}
        q2, message2 = _run(bending, q1, [reach, *cons], FTOL_EXACT)
        error2 = _distance(model, q2, goal)
        if error2 <= tolerance and _feasible(model, q2, cons):
            best, best_error, message = q2, error2, message2
    pistons = statics.pistons_for(model, best).x
    reached = best_error <= tolerance and _feasible(model, best, cons)
    return IKResult(
        q=best,
        pistons=pistons,
        tip=tip_jacobian(model, best)[0],
        error=best_error,
        success=bool(reached and np.all(np.isfinite(pistons))),
        stable=_stable(model, best, pistons),
        message=message,
    )


def _distance(model: ArmModel, q: np.ndarray, goal: np.ndarray) -> float:
    return float(np.linalg.norm(tip_jacobian(model, q)[0] - goal))


def curve_targets(curve: np.ndarray, arc_length: np.ndarray) -> np.ndarray:
    """The polyline's points (M, 3) at the arc lengths from its first point (held at its end)."""
    curve = np.asarray(curve, dtype=float)
    if curve.ndim != 2 or curve.shape[1] != 3 or len(curve) < 2:
        raise ValueError(f"curve: shape {curve.shape}, (M >= 2, 3) expected")
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])
    return np.stack([np.interp(arc_length, s, curve[:, k]) for k in range(3)], axis=-1)


def fit_shape(
    model: ArmModel,
    curve: np.ndarray,
    start: np.ndarray | None = None,
    margin: float = MARGIN,
    per_segment: int = 4,
) -> ShapeFit:
    """q whose backbone best follows `curve` (M, 3) from the base: module docstring.
    `per_segment` arc points per segment (xi = 0 ... 1) besides its endplate."""
    where = stations(model, per_segment)
    targets = curve_targets(curve, where.arc_length)
    count = len(where.segment)
    scale = 1.0 / (count * model.length**2)

    def objective(q: np.ndarray) -> tuple[float, np.ndarray]:
        p, J = points(model, q, where, jacobian=True)
        assert J is not None
        e = p - targets
        grad = 2.0 * scale * np.einsum("pi,pin->n", e, J)
        return float(scale * np.sum(e * e)), grad

    cons = constraints(model, margin)
    q0 = np.zeros(model.n_q) if start is None else np.asarray(start, dtype=float)
    q, message = _run(objective, q0, cons, FTOL_APPROACH)
    p, _ = points(model, q, where)
    d = np.linalg.norm(p - targets, axis=-1)
    pistons = statics.pistons_for(model, q).x
    return ShapeFit(
        q=q,
        pistons=pistons,
        rms=float(np.sqrt(np.mean(d * d))),
        max_error=float(np.max(d)),
        success=bool(_feasible(model, q, cons) and np.all(np.isfinite(pistons))),
        stable=_stable(model, q, pistons),
        message=message,
    )
