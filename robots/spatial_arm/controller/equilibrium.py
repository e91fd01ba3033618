"""Static equilibria of the spatial arm at given pistons, the bend limit included.

At fixed pistons x the equilibria are the stationary points of the total potential U(q) =
E_gravity + sum k theta^2 / 2 + E_gas (statics.py); the damped arm settles into a minimum. With
the bend limit |theta_s| <= theta_max (ArmBody's: a segment reaching it rests there, held by a
reaction along its normal), the arm's rest is a minimum of U on that set.

Method: Newton's method on U, globalised: the Newton matrix is U's Hessian (statics.stiffness),
its eigenvalues taken in magnitude and floored so that every step descends; each step is capped
at MAX_STEP per coordinate and halved until U falls (Armijo, within rounding). From a nearby
start it therefore converges to the minimum the damped dynamics would reach. The limit is an
active set: a segment found beyond theta_max is put on it, parametrised by its bending direction
gamma alone ((theta_x, theta_y) = theta_max (cos gamma, sin gamma); planar: held at +-theta_max),
and Newton runs again in those reduced coordinates (gradient D^T r, Hessian D^T H D plus the
curvature of the circle, -r_s . q_s); a segment whose reaction -n . r_s turns negative (U falls
inwards) is released; until no segment changes.

Shapes: pistons (..., n_q); the batch is solved together (vectorised), each configuration with
its own step lengths and active set.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from robots.spatial_arm.controller import statics
from robots.spatial_arm.controller.model import ArmModel

NEWTON_ITERATIONS = 60
LINE_SEARCH_HALVINGS = 40
STEP_TOLERANCE = 1e-13  # [rad] a full Newton step below this ends the solve
MAX_STEP = 0.5  # [rad] per coordinate and Newton step
EIGEN_FLOOR = 1e-9  # [N m/rad] smallest curvature a Newton step may assume
DUMMY_CURVATURE = 1e6  # [N m/rad] the unused coordinate of a segment on its limit
ARMIJO = 1e-4
LIMIT_ROUNDS = 8
LIMIT_SLACK = 1e-12  # [rad] a bend beyond theta_max by more puts the segment on its limit
REACTION_SLACK = 1e-12  # [N m] a reaction below minus this releases it


@dataclass(frozen=True)
class Equilibrium:
    """Static equilibria (..., n_q) at a batch of pistons: the largest residual left once the
    limits' reactions are counted [N m], converged, the smallest eigenvalue of the (reduced)
    Hessian of U [N m/rad] (> 0: a stable rest), which segments rest on their limit and the
    limits' reactions there (..., N) [N m], and the Newton iterations of the longest solve."""

    q: np.ndarray
    residual: np.ndarray
    converged: np.ndarray
    min_eigenvalue: np.ndarray
    on_limit: np.ndarray
    reaction: np.ndarray
    iterations: int

    @property
    def stable(self) -> np.ndarray:
        return self.min_eigenvalue > 0.0

    @property
    def ok(self) -> np.ndarray:
        """Converged to a stable rest."""
        return self.converged & self.stable


# ------------------------------------------------------------------ reduced coordinates


def _to_q(model: ArmModel, z: np.ndarray, on: np.ndarray) -> np.ndarray:
    """q of the reduced coordinates z (B, n_q): a spatial segment on its limit keeps its
    direction gamma in its first slot; a planar one its fixed bend."""
    if model.planar:
        return z
    full = model.full(z).copy()
    gamma = full[..., 0].copy()
    full[..., 0] = np.where(on, model.theta_max * np.cos(gamma), full[..., 0])
    full[..., 1] = np.where(on, model.theta_max * np.sin(gamma), full[..., 1])
    return model.reduce(full)


def _to_z(model: ArmModel, q: np.ndarray, on: np.ndarray) -> np.ndarray:
    """The reduced coordinates of q (B, n_q) with the segments `on` put on their limit."""
    full = model.full(q).copy()
    if model.planar:
        full[..., 0] = np.where(on, np.sign(full[..., 0]) * model.theta_max, full[..., 0])
        return model.reduce(full)
    gamma = np.arctan2(full[..., 1], full[..., 0])
    full[..., 0] = np.where(on, gamma, full[..., 0])
    full[..., 1] = np.where(on, 0.0, full[..., 1])
    return model.reduce(full)


def _tangent(model: ArmModel, z: np.ndarray, on: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """dq/dz (B, n_q, n_q) and the mask of unused reduced coordinates (B, n_q)."""
    n, nd = model.n_q, model.n_dof
    D = np.broadcast_to(np.eye(n), (len(z), n, n)).copy()
    dummy = np.zeros(z.shape, dtype=bool)
    for s in range(model.n_segments):
        i, rows = s * nd, on[:, s]
        if not np.any(rows):
            continue
        dummy[rows, i + nd - 1] = True
        if model.planar:
            D[rows, i, i] = 0.0
            continue
        gamma = z[rows, i]
        D[rows, i, i] = -model.theta_max * np.sin(gamma)
        D[rows, i + 1, i] = model.theta_max * np.cos(gamma)
        D[rows, i + 1, i + 1] = 0.0
    return D, dummy


def reactions(model: ArmModel, q: np.ndarray, r: np.ndarray, on: np.ndarray) -> np.ndarray:
    """The limits' reactions lambda_s = -n_s . r_s (B, N) of the segments `on` (0 elsewhere),
    n_s the outward normal q_s / |q_s|, r the residual dU/dq."""
    qf, rf = model.full(q), model.full(r)
    theta = np.maximum(np.linalg.norm(qf, axis=-1), 1e-300)
    lam = -np.sum(qf * rf, axis=-1) / theta
    return np.where(on, lam, 0.0)


# ------------------------------------------------------------------ Newton


def _direction(model, z, x, on):
    """The modified Newton step in z, the reduced Hessian's smallest eigenvalue, the gradient."""
    q = _to_q(model, z, on)
    r = statics.residual(model, q, x)
    H = statics.stiffness(model, q, x)
    D, dummy = _tangent(model, z, on)
    grad = np.einsum("bji,bj->bi", D, r)
    Hz = np.einsum("bji,bjk,bkl->bil", D, H, D)
    curvature = np.zeros(z.shape)
    if not model.planar:
        circle = -np.sum(model.full(r) * model.full(q), axis=-1)  # -r_s . q_s
        curvature[:, 0 :: model.n_dof] = np.where(on, circle, 0.0)
    curvature = np.where(dummy, DUMMY_CURVATURE, curvature)
    Hz = Hz + curvature[..., None] * np.eye(model.n_q)
    lam, vec = np.linalg.eigh(Hz)
    coeff = np.einsum("bji,bj->bi", vec, grad) / np.maximum(np.abs(lam), EIGEN_FLOOR)
    step = -np.einsum("bij,bj->bi", vec, coeff)
    step = np.where(dummy, 0.0, step)
    biggest = np.max(np.abs(step), axis=-1, keepdims=True)
    step = step * np.minimum(1.0, MAX_STEP / np.maximum(biggest, 1e-300))
    return step, lam[:, 0], grad


def _line_search(
    U_of: Callable[[np.ndarray, np.ndarray], np.ndarray],
    z: np.ndarray,
    step: np.ndarray,
    slope: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Each row's step halved until U falls by Armijo's rule (within rounding); U_of(z, rows)."""
    rows = np.arange(len(z))
    U = U_of(z, rows)
    alpha = np.ones(len(z))
    pending = np.ones(len(z), dtype=bool)
    out = z.copy()
    slack = 1e-13 * (1.0 + np.abs(U))
    for _ in range(LINE_SEARCH_HALVINGS):
        idx = rows[pending]
        trial = z[idx] + alpha[idx, None] * step[idx]
        good = U_of(trial, idx) <= U[idx] + ARMIJO * alpha[idx] * slope[idx] + slack[idx]
        out[idx[good]] = trial[good]
        pending[idx[good]] = False
        alpha[pending] *= 0.5
        if not np.any(pending):
            break
    alpha[pending] = 0.0
    return out, alpha


def _newton(
    model: ArmModel, x: np.ndarray, z: np.ndarray, on: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int]:
    """Minimise U in the reduced coordinates with `on` fixed: z, converged, iterations."""
    z = z.copy()
    active = np.ones(len(z), dtype=bool)
    iterations = 0
    while iterations < NEWTON_ITERATIONS and np.any(active):
        iterations += 1
        idx = np.flatnonzero(active)
        za, xa, ona = z[idx], x[idx], on[idx]
        step, _, grad = _direction(model, za, xa, ona)

        def U_of(
            trial: np.ndarray, rows: np.ndarray, on: np.ndarray = ona, x: np.ndarray = xa
        ) -> np.ndarray:
            return statics.potential(model, _to_q(model, trial, on[rows]), x[rows])

        slope = np.einsum("bi,bi->b", grad, step)
        z[idx], alpha = _line_search(U_of, za, step, slope)
        done = (alpha == 1.0) & (np.max(np.abs(step), axis=-1) <= STEP_TOLERANCE)
        active[idx[done]] = False
    return z, ~active, iterations


def static_equilibrium(
    model: ArmModel, pistons: np.ndarray, q0: np.ndarray | None = None
) -> Equilibrium:
    """The arm's rests at the pistons (..., n_q) [m], each from q0 (default straight; broadcast
    to the pistons' batch): module docstring."""
    pistons = np.asarray(pistons, dtype=float)
    if pistons.shape[-1] != model.n_q:
        raise ValueError(f"pistons: {pistons.shape[-1]} values for the arm's {model.n_q} pairs")
    batch = pistons.shape[:-1]
    x = pistons.reshape(-1, model.n_q)
    start = np.zeros(model.n_q) if q0 is None else np.asarray(q0, dtype=float)
    z = np.array(np.broadcast_to(start, pistons.shape).reshape(x.shape))
    on = np.zeros((len(x), model.n_segments), dtype=bool)
    converged = np.zeros(len(x), dtype=bool)
    todo = np.arange(len(x))
    iterations = 0
    for _ in range(LIMIT_ROUNDS):
        z[todo], converged[todo], used = _newton(model, x[todo], z[todo], on[todo])
        iterations = max(iterations, used)
        q = _to_q(model, z[todo], on[todo])
        lam = reactions(model, q, statics.residual(model, q, x[todo]), on[todo])
        engage = ~on[todo] & (model.bend_angles(q) > model.theta_max + LIMIT_SLACK)
        release = on[todo] & (lam < -REACTION_SLACK)
        changed = np.any(engage | release, axis=-1)
        if not np.any(changed):
            break
        rows = todo[changed]
        on[rows] = (on[rows] | engage[changed]) & ~release[changed]
        z[rows] = _to_z(model, q[changed], on[rows])
        converged[rows] = False
        todo = rows
    return _result(model, x, z, on, converged, iterations, batch)


def _result(model, x, z, on, converged, iterations, batch) -> Equilibrium:
    q = _to_q(model, z, on)
    r = statics.residual(model, q, x)
    lam = reactions(model, q, r, on)
    normal = model.full(q) / np.maximum(model.bend_angles(q), 1e-300)[..., None]
    free = r + model.reduce(lam[..., None] * normal)
    _, lam_min, _ = _direction(model, z, x, on)
    shaped = {"converged": converged, "min_eigenvalue": lam_min}
    return Equilibrium(
        q=q.reshape(*batch, model.n_q),
        residual=np.max(np.abs(free), axis=-1).reshape(batch),
        on_limit=on.reshape(*batch, model.n_segments),
        reaction=lam.reshape(*batch, model.n_segments),
        iterations=iterations,
        **{name: value.reshape(batch) for name, value in shaped.items()},
    )
